"""Reports: the paper's Tables 3–7 beside our runs, and accuracy vs wall-clock time.

``python -m eventrecon.report DIR... [--out DIR]`` (or :func:`build_report`;
default output ``multirun/report/``, git-ignored)
gathers every ``metrics.json`` under the given folders (Hydra multirun job folders),
writes ``table3.md``/``.tex`` … ``table7.md``/``.tex`` in the paper's layout (paper,
ours as mean ± 95 % interval over seeds, Δ; "—" for missing runs, "collapsed" / "failed"
for runs that are not results), ``accuracy_vs_time.png`` / ``.md`` and ``findings.md``
(the paper's claims, checked). Modules: :mod:`.paper` (the paper's numbers),
:mod:`.runs` (collecting run folders), :mod:`.stats` (means, intervals),
:mod:`.tables`, :mod:`.curves` (with :mod:`.budgets`: each backbone at equal
training time), :mod:`.findings`, :mod:`.collapses`, :mod:`.compute`
(what the sweeps cost), :mod:`.format`.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from pathlib import Path

from eventrecon.common.errors import InputError
from eventrecon.report.collapses import collapsed_cells, collapsed_cells_markdown
from eventrecon.report.compute import sweep_costs, sweep_costs_markdown
from eventrecon.report.curves import DEFAULT_LEVELS, write_accuracy_vs_time
from eventrecon.report.findings import (
    check_findings,
    findings_markdown,
    row_differences,
    row_differences_markdown,
)
from eventrecon.report.paper import PAPER_TABLES
from eventrecon.report.runs import (
    Run,
    collect_runs,
    current_runs,
    read_curve,
    read_run,
    versions_markdown,
    write_run,
)
from eventrecon.report.tables import REAL_SCENE, build_table, to_latex, to_markdown, write_tables

log = logging.getLogger(__name__)

__all__ = [
    "PAPER_TABLES",
    "Run",
    "build_report",
    "build_table",
    "collect_runs",
    "read_curve",
    "read_run",
    "to_latex",
    "to_markdown",
    "write_run",
]


def build_report(
    dirs: Iterable[str | Path],
    out: str | Path,
    tables: Sequence[str] = tuple(PAPER_TABLES),
    real_scene: str = REAL_SCENE,
    levels: Sequence[float] = DEFAULT_LEVELS,
    curves_experiment: str | None = "table3",
) -> list[Path]:
    """Collect the runs under ``dirs`` and write every table and the accuracy-vs-time
    figure and table (``loss=full`` runs of ``curves_experiment``) into ``out``.
    Returns the written paths. Raises :class:`~eventrecon.common.errors.InputError` before writing
    anything when none of ``dirs`` exists (a typo, or no sweep run yet): the tables would
    be empty, and written to ``docs/results`` they would replace the committed ones. (Folders
    that exist but hold no run still give tables of "—", as for missing cells.)"""
    folders = [Path(d) for d in dirs]
    if not any(d.is_dir() for d in folders):
        raise InputError(", ".join(map(str, folders)), "run folders",
                         "at least one existing folder of runs (make some with python train.py "
                         "-m experiment=table3 scale=cpu; the committed records: python -m "
                         "eventrecon.report docs/results/runs)", "no such folder")
    runs = current_runs(collect_runs(folders))
    log.info("found %d runs (%d ok)", len(runs), sum(r.ok for r in runs))
    paths = write_tables(runs, out, tables, real_scene=real_scene)
    paths += write_accuracy_vs_time(runs, out, levels, curves_experiment)
    findings = Path(out) / "findings.md"
    sections = [row_differences_markdown(row_differences(runs)),
                collapsed_cells_markdown(collapsed_cells(runs)), versions_markdown(runs),
                sweep_costs_markdown(sweep_costs(runs))]
    findings.write_text("\n".join([findings_markdown(check_findings(runs)),
                                   *(s for s in sections if s)]))
    return [*paths, findings]
