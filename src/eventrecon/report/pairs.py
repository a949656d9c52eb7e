"""Pairs of runs and the paper's difference for the same comparison.

A comparison of two settings ``a`` and ``b`` (predicates over runs) is made over the
(scene, seed) pairs where both runs were scored with the same method version: a pair
across versions would count the method's change as the settings' difference. Beside it,
the paper's own difference for the cells our scenes stand for
(:meth:`~.paper.PaperTable.difference`), the pairs that would resolve it at our spread
(:func:`.stats.pairs_to_resolve`), and a note where a paper cell behind it repeats
another row's in every metric (:meth:`~.paper.PaperTable.repeated`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

from eventrecon.report.format import fmt
from eventrecon.report.paper import PAPER_TABLES
from eventrecon.report.runs import Run
from eventrecon.report.stats import MeanCI, mean_ci, pairs_to_resolve
from eventrecon.report.tables import paper_column

__all__ = ["paired", "paper_difference", "against_paper", "inside", "needed_text"]


def _scored(runs: Sequence[Run], pick: Callable[[Run], bool]) -> dict[tuple, Run]:
    """``(scene, seed) → run`` of the scored runs that ``pick`` selects (newest wins)."""
    out: dict[tuple, Run] = {}
    for r in sorted(runs, key=lambda r: r.recency):
        if r.ok and pick(r):
            out[(r.scene, r.record.get("seed"))] = r
    return out


def paired(runs: Sequence[Run], a: Callable[[Run], bool], b: Callable[[Run], bool],
           metric: str | Callable[[Run], float | None] = "psnr") -> tuple[MeanCI | None, int]:
    """Mean ± interval of ``metric(a) − metric(b)`` over common (scene, seed) pairs made
    with the same method version (a pair across versions would count the method's change
    as the rows' difference), and the number of runs of either side that were not scored
    (collapsed or failed). ``metric``: a field of ``metrics.json`` or a function of the
    run (a pair where either side gives ``None`` is left out)."""
    value = metric if callable(metric) else (lambda r: r.metric(metric))
    lost = sum(1 for r in runs if not r.ok and (a(r) or b(r)))
    diffs = [va - vb for _, ra, rb in _pairs(runs, a, b)
             if (va := value(ra)) is not None and (vb := value(rb)) is not None]
    return (mean_ci(diffs) if diffs else None), lost


def _pairs(runs: Sequence[Run], a: Callable[[Run], bool], b: Callable[[Run], bool]
           ) -> list[tuple[tuple, Run, Run]]:
    """``((scene, seed), run a, run b)`` for every pair of scored runs that trained as one
    method version (:meth:`~eventrecon.report.runs.Run.shares_version`: a version-3 record
    that version 4 did not change pairs with runs of either)."""
    ra, rb = _scored(runs, a), _scored(runs, b)
    return [(k, ra[k], rb[k]) for k in ra.keys() & rb.keys() if ra[k].shares_version(rb[k])]


def _paper_columns(runs: Sequence[Run], table: str, a: Callable[[Run], bool],
                   b: Callable[[Run], bool]) -> list[str]:
    """The paper columns that the scenes of our pairs stand for."""
    scenes = {k[0] for k, _, _ in _pairs(runs, a, b)}
    return sorted({c for sc in scenes if (c := paper_column(table, sc))})


def paper_difference(runs: Sequence[Run], table: str, labels: tuple[str, str],
                     a: Callable[[Run], bool], b: Callable[[Run], bool],
                     metric: str) -> float | None:
    """The paper's ``labels[0] − labels[1]`` in ``metric``, averaged over the paper
    columns that the scenes of our pairs stand for (``None`` where it has none)."""
    return PAPER_TABLES[table].difference(*labels, metric, _paper_columns(runs, table, a, b))


def against_paper(d: MeanCI | None, runs: Sequence[Run], table: str, labels: tuple[str, str],
                  a: Callable[[Run], bool], b: Callable[[Run], bool], metric: str
                  ) -> tuple[float | None, int | None, str]:
    """The paper's difference for a comparison (:func:`paper_difference`), the pairs
    that would resolve it at the spread of ``d``, and a note where one of the paper's
    cells behind it repeats another row's (:meth:`~.paper.PaperTable.repeated`): which,
    and the paper's difference without those columns."""
    t, cols = PAPER_TABLES[table], _paper_columns(runs, table, a, b)
    paper = t.difference(*labels, metric, cols)            # = paper_difference, paired once
    needed = pairs_to_resolve(d, paper) if d is not None and paper is not None else None
    copies = list(dict.fromkeys(           # once per pair of rows, in either order
        f"{c} " + " = ".join(f"`{x}`" for x in sorted((lab, other)))
        for c in cols for lab in labels
        if (other := t.repeated(lab, c))))
    note = ""
    if paper is not None and copies:
        clean = t.difference(*labels, metric, cols, skip_repeated=True)
        it = "it" if len(copies) == 1 else "them"
        note = (f"the paper repeats a cell in every metric ({'; '.join(copies)}); " + (
            f"no column is left without {it}" if clean is None else
            f"without {it} the paper's difference is {fmt(clean, 2 if metric == 'psnr' else 3)}"
            f" (inside ours: {inside(clean, d).strip('*')})"))
    return paper, needed, note


def inside(paper: float | None, d: MeanCI | None) -> str:
    """Whether the paper's difference lies in our 95 % interval: "yes", "**no**" (our
    runs rule it out at this scale) or "—"."""
    if paper is None or d is None or d.half is None:
        return "—"
    return "yes" if d.low <= paper <= d.high else "**no**"


def needed_text(needed: int | None, d: MeanCI | None) -> str:
    """Pairs needed, for a table: "—" where it cannot be said, "met" where ``d`` has them."""
    if needed is None:
        return "—"
    return "met" if d is not None and d.n >= needed else str(needed)
