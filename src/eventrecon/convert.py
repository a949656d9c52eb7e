"""Convert recordings of the camera rig into the published dataset layout.

``python -m eventrecon.convert aedat4 --inputs cam0.aedat4 … cam5.aedat4 --out DIR
[--start-us S] [--end-us E] [--fps 5] [--background-us B] [--camdict camdict.json]
[--segments 5] [--sync-tolerance-us 100]``

One AEDAT4 recording per camera; the steps (align, cut, normalise, frames, background,
triggers) and what ``meta.json`` records are in :mod:`eventrecon.data.recordings`.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from eventrecon.common.errors import InputError
from eventrecon.data.recordings import convert_aedat4

__all__ = ["main"]

log = logging.getLogger(__name__)


def main(argv: Sequence[str] | None = None) -> int:
    """CLI entry (``python -m eventrecon.convert aedat4 ...``); 2 on bad input."""
    p = argparse.ArgumentParser(prog="python -m eventrecon.convert",
                                description="convert rig recordings to the published layout")
    sub = p.add_subparsers(dest="fmt", required=True)
    a = sub.add_parser("aedat4", help="one AEDAT4 recording per camera")
    a.add_argument("--inputs", nargs="+", required=True, type=Path)
    a.add_argument("--out", required=True, type=Path)
    a.add_argument("--start-us", type=int, default=0, help="cut start, µs into the shared span")
    a.add_argument("--end-us", type=int, default=None, help="cut end, µs into the shared span")
    a.add_argument("--fps", type=float, default=5.0, help="RGB reference frames per second")
    a.add_argument("--background-us", type=int, default=None,
                   help="empty-scene time, µs into the shared span")
    a.add_argument("--camdict", type=Path, default=None, help="the rig's camdict.json")
    a.add_argument("--split", default="train")
    a.add_argument("--no-bayer", dest="bayer", action="store_false",
                   help="event pixels are monochrome (not a DAVIS 346C)")
    a.add_argument("--overwrite", action="store_true")
    a.add_argument("--segments", type=int, default=5,
                   help="equal overlapping training segments written to meta.json")
    a.add_argument("--sync-tolerance-us", type=int, default=100,
                   help="largest disagreement of the cameras' external triggers")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        out = convert_aedat4(args.inputs, args.out, args.start_us, args.end_us, args.fps,
                             args.background_us, args.camdict, args.split, args.bayer,
                             args.overwrite, args.segments, args.sync_tolerance_us)
    except InputError as e:
        sys.stderr.write(f"error: {e}\n")
        return 2
    log.info("wrote %s", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
