"""Every table cell with collapsed runs, set beside the paper's value for that cell.

A collapse is expected only where the paper's own run failed: a cell the paper reports
:data:`PAPER_FAILURE_DB` or more below the best cell of its column (Static Lego's w/o
L_acc and only L_event). This is the check of "no cell collapses unless the paper's own
cell does".
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from eventrecon.report.format import fmt, markdown_table
from eventrecon.report.paper import PAPER_TABLES
from eventrecon.report.rows import ROW_OF
from eventrecon.report.runs import Run
from eventrecon.report.tables import paper_column

__all__ = ["PAPER_FAILURE_DB", "CollapsedCell", "collapsed_cells", "collapsed_cells_markdown"]

#: A paper cell this many dB or more below the best cell of its column counts as a failure
#: of the paper's own run (e.g. Static Lego: w/o L_acc 16.06 and only L_event 16.50 against
#: the full model's 23.86).
PAPER_FAILURE_DB = 5.0

@dataclass
class CollapsedCell:
    """A table cell with collapsed runs, beside the paper's value for the same cell.

    ``paper_gap`` is the paper's best PSNR in that column minus the paper's PSNR for the
    cell (``None`` when the paper has no such cell); ``paper_fails`` says whether the
    gap is at least :data:`PAPER_FAILURE_DB`, i.e. the paper's own run failed there too.
    """

    table: str
    row: str
    scene: str
    collapsed_seeds: list[int]
    runs: int
    paper_psnr: float | None
    paper_gap: float | None

    @property
    def paper_fails(self) -> bool | None:
        return None if self.paper_gap is None else self.paper_gap >= PAPER_FAILURE_DB


def collapsed_cells(runs: Sequence[Run]) -> list[CollapsedCell]:
    """Every (table, row, scene) cell of Tab. 3–7 with at least one collapsed run, with the
    paper's PSNR for the cell and its gap to the best of the paper's column — the check of
    "no cell collapses unless the paper's own cell does"."""
    cells: dict[tuple[str, str, str], dict[int, Run]] = {}
    for r in sorted(runs, key=lambda r: r.recency):  # a re-run of a seed replaces it
        if r.experiment in ROW_OF and (row := ROW_OF[r.experiment](r, r.experiment)):
            cells.setdefault((r.experiment, row, r.scene), {})[int(r.record.get("seed") or 0)] = r
    out = []
    for (table, row, scene), members in sorted(cells.items()):
        seeds = sorted(seed for seed, r in members.items() if r.status == "collapsed")
        if not seeds:
            continue
        paper, column = PAPER_TABLES[table], paper_column(table, scene)
        value = paper.value(row, column) if column else None
        best = max((v[0] for k, v in paper.values.items() if k[1] == column), default=None)
        gap = None if value is None or best is None else best - value[0]
        out.append(CollapsedCell(table, row, scene, seeds, len(members),
                                 value[0] if value else None, gap))
    return out


def collapsed_cells_markdown(cells: Sequence[CollapsedCell]) -> str:
    """:func:`collapsed_cells` as a Markdown section ("" when nothing collapsed)."""
    if not cells:
        return ""
    verdict = {True: "yes", False: "**no**", None: "—"}
    rows = [[c.table, c.row, f"`{c.scene}`", f"{len(c.collapsed_seeds)}/{c.runs}",
             ", ".join(map(str, c.collapsed_seeds)), fmt(c.paper_psnr, 2),
             fmt(c.paper_gap, 2), verdict[c.paper_fails]] for c in cells]
    header = ["table", "row", "scene", "collapsed / runs", "seeds", "paper PSNR",
              "paper: column best − cell (dB)", "paper's cell fails too"]
    return ("## Collapsed cells against the paper's\n\n" + markdown_table(header, rows)
            + f"\n\n- The paper's cell fails too when it lies {PAPER_FAILURE_DB:g} dB or more "
              "below the best cell of its column; **no**: a collapse the paper does not "
              "have.\n")
