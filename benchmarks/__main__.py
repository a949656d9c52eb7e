"""``python -m benchmarks [NAME [ARGS...]]``: run one benchmark (or all) with its own arguments.

    python -m benchmarks                      # every benchmark with its defaults
    python -m benchmarks step --only ngp      # the project's training step, one backbone
    python -m benchmarks sim --quick          # simulator, default size only
    python -m benchmarks fields --help        # a benchmark's own options
    python -m benchmarks zoo --budgets 60 180 600 --out zoo.md   # quality per second
    python -m benchmarks compile              # torch.compile / bf16 vs eager (NeRF MLP)

``make bench ARGS="step --profile"`` passes ARGS here. NAME is the part after ``bench_``
of a module in this folder. Benchmarks that read finished runs (``NEEDS_RUNS``: ``heldout``)
run only when named.
"""

from __future__ import annotations

import importlib
import logging
import pkgutil
import sys
from pathlib import Path

import eventrecon
from eventrecon.common.errors import InputError
from eventrecon.common.malloc import retain_freed_memory

log = logging.getLogger("benchmarks")


def available() -> list[str]:
    """Names of the benchmarks (``bench_<name>.py`` beside this file)."""
    here = Path(__file__).resolve().parent
    return sorted(m.name[len("bench_"):] for m in pkgutil.iter_modules([str(here)])
                  if m.name.startswith("bench_"))


def foreign_package(bench_dir: Path, package_file: Path) -> str | None:
    """A warning when ``eventrecon`` (its ``__init__.py`` at ``package_file``) comes from
    another checkout than the benchmarks in ``bench_dir``, ``None`` when it is the same
    one (``bench_dir/../src/eventrecon``) or that checkout has no ``src``. A `git
    worktree` of an older commit imports the virtual environment's editable install,
    the main checkout's code, unless ``PYTHONPATH`` names its own ``src``: an A/B
    timing would then run the new code twice."""
    own = bench_dir.resolve().parent / "src"
    used = package_file.resolve().parent
    if not (own / "eventrecon").is_dir() or used == (own / "eventrecon").resolve():
        return None
    return (f"benchmarks from {bench_dir.resolve()} time eventrecon from {used}, another "
            f"checkout: set PYTHONPATH={own} to time this checkout's code")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("eventrecon").setLevel(logging.WARNING)
    retain_freed_memory()
    warning = foreign_package(Path(__file__).parent, Path(eventrecon.__file__))
    if warning:
        log.warning(warning)
    names = available()
    if argv and argv[0] in ("-h", "--help"):
        log.info("%s\nbenchmarks: %s", __doc__, ", ".join(names))
        return 0
    if argv and argv[0] not in names:
        log.error("unknown benchmark %r: expected one of %s", argv[0], ", ".join(names))
        return 2
    todo = [(argv[0], argv[1:])] if argv else [(n, []) for n in names]
    for name, args in todo:
        module = importlib.import_module(f"benchmarks.bench_{name}")
        if not argv and getattr(module, "NEEDS_RUNS", False):
            log.info("== %s == skipped: it reads finished runs (python -m benchmarks %s "
                     "RUN_DIR ...)", name, name)
            continue
        log.info("== %s ==", name)
        try:
            module.main(args)
        except InputError as e:                  # a missing run folder, a bad file: one line
            log.error("%s", e)
            return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
