"""Run every ``benchmarks/bench_*.py`` module's ``main()`` (``python -m benchmarks``)."""

from __future__ import annotations

import importlib
import logging
import pkgutil
from pathlib import Path

log = logging.getLogger("benchmarks")


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    here = Path(__file__).resolve().parent
    for mod in sorted(m.name for m in pkgutil.iter_modules([str(here)])
                      if m.name.startswith("bench_")):
        log.info("== %s ==", mod)
        importlib.import_module(f"benchmarks.{mod}").main()


if __name__ == "__main__":
    main()
