"""``python -m eventrecon.report DIR... [--out DIR]``: tables and accuracy vs time.

Walks every DIR recursively for run folders (``metrics.json``, ``curve.csv``), writes
``table3.md``, ``table3.tex`` … ``table7.tex``, ``accuracy_vs_time.png`` and
``accuracy_vs_time.md`` into ``--out`` and logs each path. The default ``--out`` is
``multirun/report`` (git-ignored, beside the sweeps), so a report of local runs never
overwrites the committed results: those are rewritten only with ``--out docs/results``.
"""

from __future__ import annotations

import argparse
import logging
import sys

from eventrecon.common.errors import InputError
from eventrecon.report import PAPER_TABLES, build_report
from eventrecon.report.curves import DEFAULT_LEVELS
from eventrecon.report.tables import REAL_SCENE

log = logging.getLogger("eventrecon.report")

#: Where the report goes without ``--out``: git-ignored (``/multirun/`` in .gitignore).
DEFAULT_OUT: str = "multirun/report"


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit code (2: bad input, one line logged)."""
    ap = argparse.ArgumentParser(
        prog="python -m eventrecon.report", description=__doc__.splitlines()[0]
    )
    ap.add_argument("dirs", nargs="+", help="sweep / run folders to search for metrics.json")
    ap.add_argument(
        "--out", default=DEFAULT_OUT,
        help=f"output folder (default: {DEFAULT_OUT}, git-ignored; the committed results: "
             "--out docs/results)"
    )
    ap.add_argument("--tables", nargs="+", default=list(PAPER_TABLES), choices=list(PAPER_TABLES))
    ap.add_argument(
        "--real-scene", default=REAL_SCENE, help="our counterpart of 'Sword' (Tab. 4-6)"
    )
    ap.add_argument(
        "--levels", type=float, nargs="+", default=list(DEFAULT_LEVELS), help="PSNR levels [dB]"
    )
    ap.add_argument(
        "--curves-experiment", default="table3",
        help="sweep whose loss=full runs make the accuracy-vs-time comparison (default table3)"
    )
    ap.add_argument(
        "--copy-runs", metavar="DIR", default=None,
        help="also copy every current run's metrics.json and curve.csv below DIR (a committable "
             "record) and delete the records there that newer runs of their job supersede"
    )
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        paths = build_report(args.dirs, args.out, args.tables, args.real_scene, args.levels,
                             args.curves_experiment)
    except InputError as exc:
        log.error("%s", exc)
        return 2
    for p in paths:
        log.info("wrote %s", p)
    findings = next((p for p in paths if p.name == "findings.md"), None)
    if findings is not None:  # the report ends with the paper's claims, checked
        log.info("\n%s", findings.read_text())
    if args.copy_runs:
        from eventrecon.report.runs import collect_runs, copy_runs, current_runs, prune_superseded

        copied = copy_runs(current_runs(collect_runs(args.dirs)), args.dirs, args.copy_runs)
        pruned = prune_superseded(args.copy_runs)
        log.info("copied %d runs' metrics.json and curve.csv below %s (%d superseded pruned)",
                 len(copied), args.copy_runs, len(pruned))
    return 0


if __name__ == "__main__":
    sys.exit(main())
