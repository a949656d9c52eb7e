"""Our runs beside the paper's Tables 3–7, as Markdown and LaTeX.

A table is ``rows × column groups × metrics``; each metric shows three numbers:
the paper's, ours and ``Δ = ours − paper``. Rules:

- Which runs: those whose ``experiment`` is the table's key (``table3``...) when any
  exist, otherwise the runs tagged for no table (a run swept for one table is never
  shown in another).
- Row of a run: Tab. 3/4 by ``(model, loss)`` — a backbone other than ``nerf`` with
  ``loss=full`` gives a backbone row, ``nerf`` gives the ablation row of its loss;
  Tab. 5 by ``fps``, Tab. 6/7 by ``views`` (``loss=full`` runs; the backbone is held
  fixed like the other settings, so a sweep with ``model=hexplane`` fills the table
  too). Values that the paper does not have become extra rows (paper "—").
- Columns: Tab. 3 maps our synthetic scenes onto the paper's columns through
  ``SCENE_TO_PAPER`` (``spheres`` → "Spheres", ``static`` → "Static Lego"); paper columns
  without a counterpart show
  "—" for ours, our scenes without one get their own column with "—" for the paper.
  Tab. 4–6 pair the paper's "Sword" with the rig-like scene (``rig_lowlight`` by default),
  Tab. 7 pairs "Dress" with the synthetic scene that has the most view counts.
- Settings held fixed (views and fps for Tab. 3/4; the model and views for Tab. 5, the
  model and fps for Tab. 6/7) take the most common value among the table's runs; a
  footnote says which.
- One run per cell: ok before failed, then the newest. Missing → "—", failed → "failed",
  LPIPS unavailable → "n/a"; nothing is ever made up.
- Tab. 3's "Average" (ours) is the mean over the scene columns where that row has a value.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eventrecon.report.format import (
    DASH,
    FAILED,
    NOT_AVAILABLE,
    fmt,
    fmt_delta,
    latex_text,
    markdown_table,
)
from eventrecon.report.paper import METRIC_LABELS, PAPER_TABLES, PaperTable
from eventrecon.report.runs import Run

log = logging.getLogger(__name__)

#: Our synthetic scene → the paper's Tab. 3 column it stands for: ``static`` is, like
#: "Static Lego", a scene in which nothing moves (no events: only the frames inform it).
SCENE_TO_PAPER: dict[str, str] = {"spheres": "Spheres", "static": "Static Lego"}
#: Our counterpart of the real "Sword" scene (Tab. 4–6).
REAL_SCENE = "rig_lowlight"

_BACKBONES = {"tensorf_cp": "TensoRF-CP", "ngp": "NGP", "hexplane": "HexPlane"}
_ABLATIONS = {
    "no_clipping": "w/o clipping",
    "no_decay": "w/o decay",
    "no_multiseg": "w/o multi-segment",
    "no_sparsity": "w/o L_sparsity",
    "no_event": "w/o L_event",
    "no_acc": "w/o L_acc",
    "no_rgb": "w/o L_RGB",
    "only_event": "only L_event",
    "only_acc": "only L_acc",
    "only_rgb": "only L_RGB",
}


def method_row(run: Run, table: str) -> str | None:
    """Tab. 3/4 row label of a run's ``(model, loss)``; ``None`` if the table has no such row."""
    if run.model != "nerf":
        if run.loss != "full" or run.model not in _BACKBONES:
            return None
        name = _BACKBONES[run.model]
        label = name if table == "table3" else f"Ours ({name})"
    elif run.loss == "full":
        label = "Full Model" if table == "table3" else "Our Full Model (Final)"
    else:
        label = _ABLATIONS.get(run.loss)
    return label if label in PAPER_TABLES[table].rows else None


def _setting(v: float | str | None) -> str:
    """``5.0`` → "5", ``0.5`` → "0.5", ``None`` (the config's null) → "all", a name as is."""
    return "all" if v is None else v if isinstance(v, str) else f"{v:g}"


def _setting_row(attr: str) -> Callable[[Run, str], str | None]:
    def row(run: Run, table: str) -> str | None:
        return _setting(getattr(run, attr)) if run.loss == "full" else None

    return row


#: How a run finds its row, and which run settings are held fixed, per table.
ROW_OF: dict[str, Callable[[Run, str], str | None]] = {
    "table3": method_row,
    "table4": method_row,
    "table5": _setting_row("fps"),
    "table6": _setting_row("views"),
    "table7": _setting_row("views"),
}
FIXED: dict[str, tuple[str, ...]] = {
    "table3": ("views", "fps"),
    "table4": ("views", "fps"),
    "table5": ("model", "views"),
    "table6": ("model", "fps"),
    "table7": ("model", "fps"),
}


@dataclass(frozen=True)
class Group:
    """A column group: the paper's column (or ``None``) paired with our scene (or ``None``)."""

    name: str
    paper_column: str | None
    scene: str | None


@dataclass
class Cell:
    """Paper values, our values (``None`` entries = unavailable), failed flag, the run."""

    paper: tuple[float, ...] | None
    ours: tuple[float | None, ...] | None = None
    failed: bool = False
    run: Run | None = None


@dataclass
class BuiltTable:
    """A paper table filled with our runs: ``cells[(row, group.name)]`` plus footnotes."""

    paper: PaperTable
    rows: list[str]
    groups: list[Group]
    cells: dict[tuple[str, str], Cell]
    notes: list[str] = field(default_factory=list)


def _pick(runs: Sequence[Run]) -> Run:
    """One run per cell: ok before failed, then the newest."""
    return max(runs, key=lambda r: (r.ok, r.mtime, str(r.path)))


def _modal_filter(runs: list[Run], attrs: Sequence[str]) -> tuple[list[Run], dict]:
    if not runs:
        return runs, {}
    mode = Counter(tuple(getattr(r, a) for a in attrs) for r in runs).most_common(1)[0][0]
    kept = [r for r in runs if tuple(getattr(r, a) for a in attrs) == mode]
    return kept, dict(zip(attrs, mode))


def _choose_scene(key: str, runs: list[Run], tagged: bool, real_scene: str) -> str | None:
    scenes = Counter(r.scene for r in runs)
    if not scenes:
        return None
    if key in ("table4", "table5", "table6"):
        if real_scene in scenes or not tagged:
            return real_scene
        return scenes.most_common(1)[0][0]
    if tagged:
        return scenes.most_common(1)[0][0]
    synthetic = [s for s in scenes if s != real_scene]
    if not synthetic:
        return None
    views = {s: len({r.views for r in runs if r.scene == s}) for s in synthetic}
    return sorted(synthetic, key=lambda s: (-views[s], -scenes[s], s))[0]


def _row_sort(label: str) -> tuple[float, str]:
    try:
        return (float(label), label)
    except ValueError:
        return (float("inf"), label)


def build_table(
    key: str,
    runs: Sequence[Run],
    real_scene: str = REAL_SCENE,
    scene_to_paper: dict[str, str] | None = None,
) -> BuiltTable:
    """Place ``runs`` into the layout of the paper's table ``key`` (``table3`` … ``table7``)."""
    paper = PAPER_TABLES[key]
    scene_to_paper = SCENE_TO_PAPER if scene_to_paper is None else scene_to_paper
    row_of = ROW_OF[key]
    tagged = [r for r in runs if r.experiment == key]
    untagged = [r for r in runs if r.experiment not in PAPER_TABLES]
    pool = [r for r in (tagged or untagged) if row_of(r, key) is not None]
    notes: list[str] = []

    if key == "table3":
        pool = [r for r in pool if r.scene != real_scene]
        paper_scenes = [c for c in paper.columns if c != paper.average_column]
        by_column = {scene_to_paper.get(s): s for s in {r.scene for r in pool}}
        groups = [Group(c, c, by_column.get(c)) for c in paper_scenes]
        extra = sorted(s for s in {r.scene for r in pool} if s not in scene_to_paper)
        groups += [Group(s, None, s) for s in extra]
        groups.append(Group(paper.average_column, paper.average_column, None))
    else:
        scene = _choose_scene(key, pool, bool(tagged), real_scene)
        pool = [r for r in pool if r.scene == scene]
        groups = [Group(paper.columns[0], paper.columns[0], scene)]

    chosen: dict[tuple[str, str], list[Run]] = {}
    for g in groups:
        if g.scene is None:
            continue
        kept, mode = _modal_filter([r for r in pool if r.scene == g.scene], FIXED[key])
        if mode:
            fixed = ", ".join(f"{k}={_setting(v)}" for k, v in mode.items())
            notes.append(f"Ours on `{g.scene}` at {fixed}.")
        empty = [v for r in kept if (v := r.metric("psnr_background")) is not None]
        if empty:
            notes.append(f"`{g.scene}` rendered empty (background only, zero density) "
                         f"scores {float(np.median(empty)):.3f} dB PSNR: a run near it "
                         "has learnt little of the scene.")
        for r in kept:
            chosen.setdefault((row_of(r, key), g.name), []).append(r)

    rows = list(paper.rows)
    extra_rows = {row for row, _ in chosen if row not in rows}
    rows += sorted(extra_rows, key=_row_sort)

    cells: dict[tuple[str, str], Cell] = {}
    lpips_notes: set[str] = set()
    for row in rows:
        for g in groups:
            cell = Cell(paper.value(row, g.paper_column) if g.paper_column else None)
            cand = chosen.get((row, g.name))
            if cand:
                run = _pick(cand)
                cell.run, cell.failed = run, not run.ok
                if run.ok:
                    cell.ours = tuple(run.metric(m) for m in paper.metrics)
                    if "lpips" in paper.metrics and run.metric("lpips") is None:
                        lpips_notes.add(str(run.record.get("lpips_note") or "not computed"))
            cells[(row, g.name)] = cell

    if paper.average_column:
        _fill_average(paper, rows, groups, cells, notes)
    for n in sorted(lpips_notes):
        notes.append(f'"{NOT_AVAILABLE}": LPIPS unavailable ({n}).')
    if not any(c.run for c in cells.values()):
        notes.append(f"No runs found for this table: our columns are all '{DASH}'.")
    return BuiltTable(paper, rows, groups, cells, notes)


def _fill_average(
    paper: PaperTable,
    rows: list[str],
    groups: list[Group],
    cells: dict[tuple[str, str], Cell],
    notes: list[str],
) -> None:
    """Ours in the average column: per row and metric, the mean over the scene columns
    where that row has a value (failed / missing / unavailable cells are left out)."""
    scene_groups = [g for g in groups if g.name != paper.average_column]
    used: dict[str, list[str]] = {}
    for row in rows:
        means: list[float | None] = []
        for m in range(len(paper.metrics)):
            vals = []
            for g in scene_groups:
                c = cells[(row, g.name)]
                if c.ours is not None and c.ours[m] is not None:
                    vals.append(c.ours[m])
                    if m == 0:
                        used.setdefault(row, []).append(g.scene)
            means.append(float(np.mean(vals)) if vals else None)
        if any(v is not None for v in means):
            cells[(row, paper.average_column)].ours = tuple(means)
    if used:
        sets = {tuple(v) for v in used.values()}
        if len(sets) == 1:
            scenes = ", ".join(f"`{s}`" for s in next(iter(sets)))
            notes.append(
                f"{paper.average_column} (ours): mean over the columns with a value: {scenes}."
            )
        else:
            per = "; ".join(f"{r}: " + ", ".join(f"`{s}`" for s in v) for r, v in used.items())
            notes.append(
                f"{paper.average_column} (ours): per row, mean over the columns with a value "
                f"({per})."
            )
        notes.append(
            f"{paper.average_column} (paper): mean over the paper's five scenes; "
            "Δ compares averages over different scene sets."
        )


def _cell_strings(cell: Cell, m: int, decimals: int) -> list[str]:
    paper = fmt(cell.paper[m], decimals) if cell.paper else DASH
    if cell.failed:
        return [paper, FAILED, DASH]
    if cell.ours is None:
        return [paper, DASH, DASH]
    ours = cell.ours[m]
    if ours is None:
        return [paper, NOT_AVAILABLE, DASH]
    delta = ours - cell.paper[m] if cell.paper else None
    return [paper, fmt(ours, decimals), fmt_delta(delta, decimals)]


def _group_title(t: BuiltTable, g: Group) -> str:
    if g.name == t.paper.average_column:
        return f"{g.name} — ours: mean over our columns with a value"
    paper = g.paper_column or f"{DASH} (no paper counterpart)"
    ours = f"`{g.scene}`" if g.scene else f"{DASH} (no counterpart run)"
    return f"{paper} — ours: {ours}"


def _group_rows(t: BuiltTable, g: Group) -> list[list[str]]:
    return [
        [row]
        + [
            s
            for m in range(len(t.paper.metrics))
            for s in _cell_strings(t.cells[(row, g.name)], m, t.paper.decimals)
        ]
        for row in t.rows
    ]


def to_markdown(t: BuiltTable) -> str:
    """The table as Markdown: one sub-table per column group, then the footnotes."""
    intro = f"_{t.paper.caption}_ Columns: paper, ours, Δ = ours − paper."
    out = [f"## {t.paper.title}", "", intro, ""]
    for g in t.groups:
        header = [t.paper.row_header] + [
            f"{METRIC_LABELS[m]} {what}"
            for m in t.paper.metrics
            for what in ("paper", "ours", "Δ")
        ]
        out += [f"### {_group_title(t, g)}", "", markdown_table(header, _group_rows(t, g)), ""]
    out += [f"- {n}" for n in t.notes]
    return "\n".join(out).rstrip() + "\n"


def to_latex(t: BuiltTable) -> str:
    """The table as LaTeX (``booktabs``): one tabular block per column group."""
    k = len(t.paper.metrics)
    spec = "l" + " rrr" * k
    lines = [r"% requires \usepackage{booktabs}", r"\begin{table}[t]", r"\centering", r"\small"]
    for g in t.groups:
        lines += [rf"\begin{{tabular}}{{{spec}}}", r"\toprule"]
        lines.append(rf"\multicolumn{{{1 + 3 * k}}}{{c}}{{{latex_text(_group_title(t, g))}}} \\")
        spans = [
            rf"\multicolumn{{3}}{{c}}{{{latex_text(METRIC_LABELS[m])}}}" for m in t.paper.metrics
        ]
        lines.append(" & ".join(["", *spans]) + r" \\")
        lines.append(" ".join(rf"\cmidrule(lr){{{2 + 3 * i}-{4 + 3 * i}}}" for i in range(k)))
        sub = [latex_text(t.paper.row_header)] + ["paper", "ours", r"$\Delta$"] * k
        lines.append(" & ".join(sub) + r" \\")
        lines.append(r"\midrule")
        for r in _group_rows(t, g):
            lines.append(" & ".join(latex_text(s) for s in r) + r" \\")
        lines += [r"\bottomrule", r"\end{tabular}", r"\medskip", ""]
    caption = latex_text(t.paper.caption + " " + " ".join(t.notes))
    lines += [rf"\caption{{{caption}}}", rf"\label{{tab:{t.paper.key}}}", r"\end{table}"]
    return "\n".join(lines) + "\n"


def write_tables(
    runs: Sequence[Run], out: str | Path, keys: Sequence[str] = tuple(PAPER_TABLES), **kw
) -> list[Path]:
    """Write ``<key>.md`` and ``<key>.tex`` for each table into ``out``; returns the paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for key in keys:
        t = build_table(key, runs, **kw)
        for suffix, text in ((".md", to_markdown(t)), (".tex", to_latex(t))):
            p = out / f"{key}{suffix}"
            p.write_text(text)
            paths.append(p)
    return paths
