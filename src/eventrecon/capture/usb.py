"""Discovery of iniVation event cameras on USB (pyusb) and the six-camera rig check.

iniVation's USB vendor id is ``0x152A``; product ids: DAVIS346 (FX3 board) ``0x841A``,
DAVIS240 (FX2 board) ``0x841B``, DVXplorer ``0x8419``. Six DAVIS346 streaming events
and frames need USB3 bandwidth (the authors' rig used two extra PCIe USB3 cards and
optical USB3 extensions), so the rig check flags every camera that enumerated on a
slower link: a USB2 port, hub or cable silently drops the link to High Speed.

Link speed is pyusb's ``Device.speed`` (libusb's negotiated speed:
``usb.util.SPEED_LOW … SPEED_SUPER``, 5 = SuperSpeed+); when the backend does not report
it, the device descriptor's ``bcdUSB`` (≥ 0x0300 for a USB3 device) is the fallback —
weaker, since a USB3 device on a USB2 port still reports its own ``bcdUSB``.

libusb itself comes from the system when it is installed, otherwise from the
``libusb-package`` wheel (a project dependency that bundles libusb-1.0), so a fresh install
needs nothing installed by hand: see :func:`default_backend`.

Everything goes through pyusb's backend interface, so tests run on a simulated bus
(``backend=`` any :class:`usb.backend.IBackend`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import usb.backend
import usb.backend.libusb0
import usb.backend.libusb1
import usb.backend.openusb
import usb.core
import usb.util

__all__ = ["INIVATION_VENDOR_ID", "PRODUCTS", "CameraInfo", "LibusbMissing", "INSTALL_HINT",
           "default_backend", "list_cameras", "check_rig", "speed_name"]

log = logging.getLogger(__name__)

INIVATION_VENDOR_ID: int = 0x152A
#: product id -> model name.
PRODUCTS: dict[int, str] = {0x841A: "DAVIS346", 0x841B: "DAVIS240", 0x8419: "DVXplorer"}
#: libusb speed code -> (name, signalling rate).
_SPEEDS: dict[int, str] = {
    usb.util.SPEED_UNKNOWN: "unknown speed",
    usb.util.SPEED_LOW: "Low Speed (1.5 Mb/s, USB1)",
    usb.util.SPEED_FULL: "Full Speed (12 Mb/s, USB1)",
    usb.util.SPEED_HIGH: "High Speed (480 Mb/s, USB2)",
    usb.util.SPEED_SUPER: "SuperSpeed (5 Gb/s, USB3)",
    5: "SuperSpeed+ (10 Gb/s, USB3.1)",
}

#: The one line shown when neither the system's libusb nor the bundled one loads.
INSTALL_HINT: str = ("no libusb backend for pyusb (neither the system's libusb nor the one "
                     "bundled by libusb-package loads): install libusb-1.0 "
                     "(Debian/Ubuntu: `sudo apt-get install libusb-1.0-0`, macOS: "
                     "`brew install libusb`, conda: `conda install -c conda-forge libusb`)")


class LibusbMissing(RuntimeError):
    """pyusb has no backend (no libusb loads); the message says how to fix it."""


def _system_libusb1() -> usb.backend.IBackend | None:
    return usb.backend.libusb1.get_backend()


def _bundled_libusb1() -> usb.backend.IBackend | None:
    """libusb-1.0 from the ``libusb-package`` wheel (``None`` if that is not installed)."""
    try:
        import libusb_package
    except ImportError:
        return None
    # not libusb_package.get_libusb1_backend(): it caches its answer for the process
    return usb.backend.libusb1.get_backend(find_library=libusb_package.find_library)


def _system_other() -> usb.backend.IBackend | None:
    """pyusb's remaining backends (openusb, libusb-0.1), tried last: they report no speed."""
    return usb.backend.openusb.get_backend() or usb.backend.libusb0.get_backend()


#: (what, loader) in order of preference.
_BACKENDS = (("system libusb-1.0", _system_libusb1),
             ("libusb-1.0 bundled by libusb-package", _bundled_libusb1),
             ("system openusb/libusb-0.1", _system_other))


def default_backend() -> usb.backend.IBackend:
    """The pyusb backend used when none is given: the system's libusb-1.0 when it loads,
    else the one bundled by ``libusb-package``, else openusb / libusb-0.1.

    Raises:
        LibusbMissing: none of them loads (message: :data:`INSTALL_HINT`).
    """
    for what, load in _BACKENDS:
        backend = load()
        if backend is not None:
            lib = getattr(getattr(backend, "lib", None), "_name", None)
            log.info("pyusb backend: %s%s", what, f" ({lib})" if lib else "")
            return backend
    raise LibusbMissing(INSTALL_HINT)


def speed_name(speed: int | None) -> str:
    """Human-readable link speed of a libusb speed code."""
    return _SPEEDS.get(speed if speed is not None else 0, f"speed code {speed}")


@dataclass(frozen=True)
class CameraInfo:
    """One iniVation camera on the bus.

    Attributes:
        model: ``DAVIS346``, ``DAVIS240``, ``DVXplorer`` or ``unknown 0x....``.
        product_id: USB product id.
        serial: the serial-number string, or ``None`` if it could not be read
            (typically missing udev permissions).
        bus, address: libusb bus number and device address.
        port_path: ``<bus>-<port>.<port>…`` as in Linux sysfs, ``?`` if unknown.
        speed: libusb speed code (``usb.util.SPEED_*``) or ``None``.
        bcd_usb: the device descriptor's USB release (``0x0300`` for USB 3.0).
        note: why the serial is missing, if it is.
    """

    model: str
    product_id: int
    serial: str | None
    bus: int | None
    address: int | None
    port_path: str
    speed: int | None
    bcd_usb: int
    note: str = ""

    @property
    def superspeed(self) -> bool:
        """Link at SuperSpeed or faster (``bcdUSB ≥ 3.0`` when the speed is unknown)."""
        if self.speed is not None and self.speed != usb.util.SPEED_UNKNOWN:
            return self.speed >= usb.util.SPEED_SUPER
        return self.bcd_usb >= 0x0300

    def describe(self) -> str:
        """One line: model, serial, bus/address, port, link speed."""
        serial = self.serial if self.serial is not None else f"? ({self.note})"
        return (f"{self.model:<9} serial {serial:<12} bus {self.bus:>3} addr {self.address:>3} "
                f"port {self.port_path:<10} {speed_name(self.speed)}")


def _serial(dev: usb.core.Device) -> tuple[str | None, str]:
    """The serial string, or ``None`` and why (pyusb reports denied access as "no langid")."""
    try:
        return dev.serial_number, ""
    except (usb.core.USBError, ValueError, NotImplementedError) as e:
        return None, (f"serial unreadable ({getattr(e, 'strerror', None) or e}); "
                      "check the udev permissions for vendor 152a")


def _port_path(dev: usb.core.Device) -> str:
    ports = getattr(dev, "port_numbers", None)
    if not ports:
        return "?" if dev.port_number is None else f"{dev.bus}-{dev.port_number}"
    return f"{dev.bus}-" + ".".join(str(p) for p in ports)


def list_cameras(backend: object | None = None) -> list[CameraInfo]:
    """All iniVation devices on the bus, sorted by (bus, port path).

    Args:
        backend: a pyusb backend (default: :func:`default_backend`, the system's libusb
            first, the bundled one second).

    Raises:
        LibusbMissing: no libusb loads (message: :data:`INSTALL_HINT`).
    """
    if backend is None:
        backend = default_backend()
    try:
        devices = list(usb.core.find(find_all=True, idVendor=INIVATION_VENDOR_ID,
                                     backend=backend))
    except usb.core.NoBackendError:
        raise LibusbMissing(INSTALL_HINT) from None
    out = []
    for dev in devices:
        serial, note = _serial(dev)
        out.append(CameraInfo(
            model=PRODUCTS.get(dev.idProduct, f"unknown 0x{dev.idProduct:04X}"),
            product_id=int(dev.idProduct), serial=serial, bus=dev.bus, address=dev.address,
            port_path=_port_path(dev), speed=dev.speed, bcd_usb=int(dev.bcdUSB), note=note))
    out.sort(key=lambda c: (c.bus or 0, c.port_path))
    log.info("found %d iniVation device(s)", len(out))
    return out


def check_rig(cameras: list[CameraInfo], expect: int = 6, model: str | None = "DAVIS346"
              ) -> list[str]:
    """Problems of a multi-camera rig; an empty list means the rig is ready.

    Flags: fewer (or more) cameras of ``model`` than ``expect`` (``model=None`` counts every
    iniVation camera), any camera not on a SuperSpeed link, duplicate serial numbers.
    """
    rig = [c for c in cameras if model is None or c.model == model]
    problems = []
    what = model or "iniVation"
    if len(rig) < expect:
        problems.append(f"missing cameras: expected {expect} {what}, found {len(rig)}")
    elif len(rig) > expect:
        problems.append(f"unexpected cameras: expected {expect} {what}, found {len(rig)}")
    for c in rig:
        if not c.superspeed:
            problems.append(
                f"{c.model} serial {c.serial or '?'} at port {c.port_path} is on "
                f"{speed_name(c.speed)}, not SuperSpeed: use a USB3 port/card and USB3 cables")
    serials = [c.serial for c in rig if c.serial]
    dups = sorted({s for s in serials if serials.count(s) > 1})
    if dups:
        problems.append(f"duplicate serial numbers {dups}")
    return problems
