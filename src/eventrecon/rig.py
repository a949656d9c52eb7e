"""Rig tools: ``python -m eventrecon.rig list | check --expect 6 | calibrate-crf ...``.

- ``list``: the iniVation cameras on USB with model, serial, bus/address, port, link speed
  ("no cameras found", exit 0, when there are none).
- ``check --expect 6``: the six-camera check; exits 1 and names every problem (missing
  cameras, a camera not on a SuperSpeed link, duplicate serials).
- ``calibrate-crf --images DIR | --csv FILE``: fits the linear CRF offset ε from an
  exposure sweep (single pixels, saturated roll-off and clipped zeros excluded), prints
  ε and saves a plot like the supplementary's Fig. 9.

libusb is the system's when it is installed, else the one bundled by ``libusb-package``.
Exit codes: 0 ok, 1 rig problems, 2 bad input or no libusb loads (one line on stderr).
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from eventrecon.capture.crf import fit_crf, load_sweep_csv, load_sweep_images, plot_crf
from eventrecon.capture.usb import LibusbMissing, check_rig, list_cameras
from eventrecon.common.errors import InputError

__all__ = ["main", "build_parser"]

log = logging.getLogger(__name__)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the three sub-commands."""
    p = argparse.ArgumentParser(prog="python -m eventrecon.rig", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    sub.add_parser("list", help="list iniVation cameras on USB")
    c = sub.add_parser("check", help="check a multi-camera rig (count, USB3 links)")
    c.add_argument("--expect", type=int, default=6, help="number of cameras (default 6)")
    c.add_argument("--model", default="DAVIS346",
                   help="camera model to count, or 'any' (default DAVIS346)")
    f = sub.add_parser("calibrate-crf", help="fit the linear CRF offset from an exposure sweep")
    src = f.add_mutually_exclusive_group(required=True)
    src.add_argument("--images", type=Path, help="folder of PNGs named by exposure time")
    src.add_argument("--csv", type=Path, help="CSV rows: exposure, v_1, ..., v_P")
    f.add_argument("--pixels", type=int, default=256, help="pixels sampled per image")
    f.add_argument("--sat-level", type=float, default=0.95, help="exclude values ≥ this (0..1)")
    f.add_argument("--floor", type=float, default=0.02, help="exclude values ≤ this (0..1)")
    f.add_argument("--plot", type=Path, default=Path("crf_fit.png"), help="plot file")
    return p


def _out(line: str) -> None:
    sys.stdout.write(line + "\n")


def main(argv: Sequence[str] | None = None, backend: object | None = None) -> int:
    """Run the CLI; ``backend`` is a pyusb backend (tests pass a simulated bus)."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s: %(message)s")
    try:
        if args.cmd in ("list", "check"):
            cams = list_cameras(backend)
            for c in cams:
                _out(c.describe())
            if not cams:
                _out("no cameras found")
            if args.cmd == "list":
                if cams:
                    _out(f"{len(cams)} iniVation camera(s)")
                return 0
            problems = check_rig(cams, args.expect, None if args.model == "any" else args.model)
            for pr in problems:
                _out(f"PROBLEM: {pr}")
            _out("rig OK" if not problems else f"{len(problems)} problem(s)")
            return 1 if problems else 0
        if args.images is not None:
            exposures, values = load_sweep_images(args.images, args.pixels)
        else:
            exposures, values = load_sweep_csv(args.csv)
        fit = fit_crf(exposures, values, args.sat_level, args.floor)
        plot_crf(exposures, values, fit, args.plot)
        _out(f"eps = {fit.eps:.5f} ({255 * fit.eps:.2f} of 255), "
             f"{int(fit.used.any(0).sum())} pixels, rms residual {fit.residual:.4f}")
        _out(f"plot: {args.plot}")
        return 0
    except (LibusbMissing, InputError) as e:
        sys.stderr.write(f"error: {e}\n")
        return 2


if __name__ == "__main__":
    sys.exit(main())
