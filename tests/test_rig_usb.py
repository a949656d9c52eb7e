"""USB discovery and the six-camera check on a simulated bus (pyusb backend interface)."""

from __future__ import annotations

import array
import sys
from dataclasses import dataclass, field

import libusb_package
import pytest
import usb.backend
import usb.backend.libusb0
import usb.backend.libusb1
import usb.backend.openusb
import usb.core
import usb.util

from eventrecon.capture.usb import (
    INSTALL_HINT,
    LibusbMissing,
    check_rig,
    default_backend,
    list_cameras,
)
from eventrecon.rig import main


@dataclass
class FakeDevice:
    """What a backend reports for one device (device descriptor fields + strings)."""

    idVendor: int
    idProduct: int
    bus: int
    address: int
    port_numbers: tuple[int, ...]
    speed: int
    serial: str | None = None
    bcdUSB: int = 0x0300
    deny_strings: bool = False  # simulate missing udev permissions
    bLength: int = 18
    bDescriptorType: int = 1
    bDeviceClass: int = 0xEF
    bDeviceSubClass: int = 2
    bDeviceProtocol: int = 1
    bMaxPacketSize0: int = 9
    bcdDevice: int = 0x0100
    iManufacturer: int = 1
    iProduct: int = 2
    bNumConfigurations: int = 1
    strings: dict = field(default_factory=dict)

    @property
    def iSerialNumber(self) -> int:
        return 3 if self.serial is not None else 0

    @property
    def port_number(self) -> int:
        return self.port_numbers[-1]


class SimulatedBus(usb.backend.IBackend):
    """A pyusb backend over a list of :class:`FakeDevice` (no hardware, no libusb)."""

    def __init__(self, devices: list[FakeDevice]):
        super().__init__()
        self.devices = devices

    def enumerate_devices(self):
        return iter(self.devices)

    def get_device_descriptor(self, dev):
        return dev

    def get_parent(self, dev):
        return None

    def open_device(self, dev):
        return dev

    def close_device(self, dev_handle):
        pass

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        dev = dev_handle
        if dev.deny_strings:
            raise usb.core.USBError("Access denied (insufficient permissions)", errno=13)
        desc_type, index = wValue >> 8, wValue & 0xFF
        assert bRequest == 0x06 and desc_type == usb.util.DESC_TYPE_STRING
        if index == 0:
            payload = (0x0409).to_bytes(2, "little")  # LANGID en-US
        else:
            payload = {1: "iniVation", 2: "DAVIS FX3", 3: dev.serial}[index].encode("utf-16-le")
        buf = bytes([2 + len(payload), usb.util.DESC_TYPE_STRING]) + payload
        n = min(len(buf), len(data))
        data[:n] = array.array("B", buf[:n])
        return n


def davis(i: int, speed: int = usb.util.SPEED_SUPER, **kw) -> FakeDevice:
    return FakeDevice(0x152A, 0x841A, bus=2 + i // 3, address=10 + i, port_numbers=(1, i + 1),
                      speed=speed, serial=kw.pop("serial", f"00000{i:03d}"), **kw)


OTHERS = [FakeDevice(0x046D, 0xC52B, 1, 3, (4,), usb.util.SPEED_FULL, serial="LOGI"),
          FakeDevice(0x0BDA, 0x8153, 1, 4, (5,), usb.util.SPEED_SUPER, serial="NIC")]


def test_lists_six_davis_with_serial_bus_port_speed():
    bus = SimulatedBus(OTHERS + [davis(i) for i in range(6)])
    cams = list_cameras(bus)
    assert [c.serial for c in cams] == [f"00000{i:03d}" for i in range(6)]  # other vendors ignored
    assert [c.bus for c in cams] == [2, 2, 2, 3, 3, 3]
    assert cams[4].port_path == "3-1.5" and cams[4].address == 14
    assert all(c.model == "DAVIS346" and c.superspeed for c in cams)
    assert check_rig(cams, expect=6) == []


def test_one_missing_is_flagged():
    cams = list_cameras(SimulatedBus([davis(i) for i in range(5)]))
    problems = check_rig(cams, expect=6)
    assert problems == ["missing cameras: expected 6 DAVIS346, found 5"]


def test_high_speed_link_is_flagged():
    devs = [davis(i) for i in range(6)]
    devs[3] = davis(3, speed=usb.util.SPEED_HIGH)
    problems = check_rig(list_cameras(SimulatedBus(devs)), expect=6)
    assert len(problems) == 1
    assert "serial 00000003 at port 3-1.4 is on High Speed (480 Mb/s, USB2)" in problems[0]


def test_other_models_do_not_count_as_rig_cameras():
    devs = [davis(i) for i in range(5)]
    devs.append(FakeDevice(0x152A, 0x8419, 4, 20, (2,), usb.util.SPEED_SUPER, serial="DVX1"))
    cams = list_cameras(SimulatedBus(devs))
    assert sorted(c.model for c in cams) == ["DAVIS346"] * 5 + ["DVXplorer"]
    assert check_rig(cams, expect=6)[0].startswith("missing cameras")
    assert check_rig(cams, expect=6, model=None) == []


def test_unreadable_serial_is_tolerated_and_duplicates_flagged():
    devs = [davis(i) for i in range(6)]
    devs[0] = davis(0, deny_strings=True)
    devs[5] = davis(5, serial="00000004")
    cams = list_cameras(SimulatedBus(devs))
    assert cams[0].serial is None and "udev permissions" in cams[0].note
    assert check_rig(cams) == ["duplicate serial numbers ['00000004']"]


def test_unknown_speed_falls_back_to_bcd_usb():
    devs = [davis(i, speed=usb.util.SPEED_UNKNOWN) for i in range(6)]
    devs[0] = davis(0, speed=usb.util.SPEED_UNKNOWN, bcdUSB=0x0200)
    problems = check_rig(list_cameras(SimulatedBus(devs)))
    assert len(problems) == 1 and "00000000" in problems[0]


def test_cli_check_exit_codes(capsys):
    ok = SimulatedBus([davis(i) for i in range(6)])
    assert main(["check", "--expect", "6"], backend=ok) == 0
    assert capsys.readouterr().out.strip().endswith("rig OK")
    bad = SimulatedBus([davis(i) for i in range(5)])
    assert main(["check", "--expect", "6"], backend=bad) == 1
    assert "PROBLEM: missing cameras: expected 6 DAVIS346, found 5" in capsys.readouterr().out
    assert main(["list"], backend=ok) == 0
    assert "6 iniVation camera(s)" in capsys.readouterr().out


def test_no_libusb_says_how_to_install_in_one_line(monkeypatch, capsys):
    import usb.backend.libusb0
    import usb.backend.libusb1
    import usb.backend.openusb
    for m in (usb.backend.libusb0, usb.backend.libusb1, usb.backend.openusb):
        monkeypatch.setattr(m, "get_backend", lambda *a, **k: None)
    with pytest.raises(LibusbMissing, match="apt-get install libusb-1.0-0"):
        list_cameras()
    assert main(["list"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and INSTALL_HINT in err


def _fake_libusb(monkeypatch, system: object | None, bundled: object | None) -> list:
    """libusb-1.0 loads from the system (``find_library=None``) and/or from libusb-package."""
    calls: list = []

    def get_backend(find_library=None):
        calls.append(find_library)
        if find_library is None:
            return system
        assert find_library is libusb_package.find_library
        return bundled

    monkeypatch.setattr(usb.backend.libusb1, "get_backend", get_backend)
    for m in (usb.backend.libusb0, usb.backend.openusb):
        monkeypatch.setattr(m, "get_backend", lambda *a, **k: None)
    return calls


def test_backend_is_the_systems_libusb_first(monkeypatch):
    system, bundled = SimulatedBus([davis(0)]), SimulatedBus([])
    calls = _fake_libusb(monkeypatch, system, bundled)
    assert default_backend() is system
    assert calls == [None]  # the bundled one is not even tried
    assert [c.serial for c in list_cameras()] == ["00000000"]


def test_backend_falls_back_to_the_bundled_libusb(monkeypatch):
    bundled = SimulatedBus([davis(1)])
    calls = _fake_libusb(monkeypatch, None, bundled)
    assert default_backend() is bundled
    assert calls == [None, libusb_package.find_library]
    assert [c.serial for c in list_cameras()] == ["00000001"]


def test_neither_backend_is_one_line_error(monkeypatch, capsys):
    _fake_libusb(monkeypatch, None, None)
    with pytest.raises(LibusbMissing, match="apt-get install libusb-1.0-0"):
        default_backend()
    monkeypatch.setitem(sys.modules, "libusb_package", None)  # wheel not installed at all
    with pytest.raises(LibusbMissing):
        default_backend()
    assert main(["check", "--expect", "6"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and INSTALL_HINT in err


def test_bundled_libusb_ships_with_the_wheel_and_loads():
    path = libusb_package.get_library_path()
    assert path is not None and path.is_file()  # a fresh install needs no system libusb
    assert usb.backend.libusb1.get_backend(find_library=libusb_package.find_library) is not None


def test_cli_no_cameras_on_the_bus(capsys):
    bus = SimulatedBus(OTHERS)  # a mouse and a NIC, no iniVation device
    assert main(["list"], backend=bus) == 0
    captured = capsys.readouterr()
    assert captured.out == "no cameras found\n" and captured.err == ""
    assert main(["check", "--expect", "6"], backend=bus) == 1
    out = capsys.readouterr().out.splitlines()
    assert out == ["no cameras found", "PROBLEM: missing cameras: expected 6 DAVIS346, found 0",
                   "1 problem(s)"]
