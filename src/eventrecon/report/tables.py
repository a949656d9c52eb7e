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
- Seeds: a cell holds one run per seed (ok before collapsed before failed, then the
  newest); ours is the mean over the seeds whose run is ``ok``, with the half-width of
  its 95 % interval (:mod:`.stats`) when there are two or more, and the column ``n``
  says how many seeds were scored of how many ran (collapsed and failed ones named).
  Missing → "—"; every seed collapsed → "collapsed", failed → "failed"; LPIPS
  unavailable → "n/a"; nothing is ever made up.
- Tab. 3's "Average" (ours) is the mean over the scene columns where that row has a
  value (its interval combines theirs, assuming independent columns).
- Below the paper-comparable columns, a *subject* section per scene: PSNR on the
  subject's region (the masks of the held-out frames) and the gain over the empty
  field, full-frame and on the subject.
- Footnotes list what the runs changed from the paper's method to fit a CPU budget
  (compressed schedules, CPU sizes), read from the runs' own records.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eventrecon.report.cells import Cell, cell_stats, fmt_ci, method_notes, per_seed
from eventrecon.report.format import (
    COLLAPSED,
    DASH,
    FAILED,
    NOT_AVAILABLE,
    fmt,
    fmt_delta,
    latex_text,
    markdown_table,
)
from eventrecon.report.paper import METRIC_LABELS, PAPER_TABLES, PaperTable
from eventrecon.report.rows import FIXED, ROW_OF, setting_label
from eventrecon.report.runs import Run
from eventrecon.report.stats import MeanCI

log = logging.getLogger(__name__)

#: Our synthetic scene → the paper's Tab. 3 column it stands for: ``static`` is, like
#: "Static Lego", a scene in which nothing moves (no events: only the frames inform it).
SCENE_TO_PAPER: dict[str, str] = {"blender": "Blender", "dress": "Dress", "spheres": "Spheres",
                                  "lego": "Lego", "static_lego": "Static Lego"}
#: Our counterpart of the real "Sword" scene (Tab. 4–6).
REAL_SCENE = "rig_lowlight"


def paper_column(table: str, scene: str) -> str | None:
    """The paper's column a scene of ours stands for, as :func:`build_table` pairs them:
    Tab. 3 by :data:`SCENE_TO_PAPER`, Tab. 4–7 by their one column.

    >>> paper_column("table3", "static_lego"), paper_column("table5", "rig_lowlight")
    ('Static Lego', 'Sword')
    """
    return SCENE_TO_PAPER.get(scene) if table == "table3" else PAPER_TABLES[table].columns[0]

@dataclass(frozen=True)
class Group:
    """A column group: the paper's column (or ``None``) paired with our scene (or ``None``)."""

    name: str
    paper_column: str | None
    scene: str | None


@dataclass
class BuiltTable:
    """A paper table filled with our runs: ``cells[(row, group.name)]`` plus footnotes."""

    paper: PaperTable
    rows: list[str]
    groups: list[Group]
    cells: dict[tuple[str, str], Cell]
    notes: list[str] = field(default_factory=list)


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
            fixed = ", ".join(f"{k}={setting_label(v)}" for k, v in mode.items())
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
                cell.runs = per_seed(cand)
                cell.ours = cell_stats(cell.runs, paper.metrics)
                for run in cell.scored:
                    if "lpips" in paper.metrics and run.metric("lpips") is None:
                        lpips_notes.add(str(run.record.get("lpips_note") or "not computed"))
            cells[(row, g.name)] = cell

    if paper.average_column:
        _fill_average(paper, rows, groups, cells, notes)
    for n in sorted(lpips_notes):
        notes.append(f'"{NOT_AVAILABLE}": LPIPS unavailable ({n}).')
    notes += method_notes([r for c in cells.values() for r in c.runs])
    if not any(c.runs for c in cells.values()):
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
    where that row has a value (failed / collapsed / missing / unavailable cells are left
    out); its half-width ``sqrt(Σ h²) / k`` when every column has one."""
    scene_groups = [g for g in groups if g.name != paper.average_column]
    used: dict[str, list[str]] = {}
    for row in rows:
        means: list[MeanCI | None] = []
        for m in range(len(paper.metrics)):
            vals = []
            for g in scene_groups:
                c = cells[(row, g.name)]
                if c.ours is not None and c.ours[m] is not None:
                    vals.append(c.ours[m])
                    if m == 0:
                        used.setdefault(row, []).append(g.scene)
            if not vals:
                means.append(None)
                continue
            halves = [v.half for v in vals]
            half = (float(np.sqrt(sum(h * h for h in halves))) / len(vals)
                    if all(h is not None for h in halves) else None)
            means.append(MeanCI(float(np.mean([v.mean for v in vals])), half,
                                min(v.n for v in vals)))
        if any(v is not None for v in means):
            avg = cells[(row, paper.average_column)]
            avg.ours = tuple(means)
            avg.runs = [r for g in scene_groups for r in cells[(row, g.name)].runs]
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
    if cell.ours is None:
        shown = {"collapsed": COLLAPSED, "failed": FAILED}.get(cell.status, DASH)
        return [paper, shown, DASH]
    ours = cell.ours[m]
    if ours is None:
        return [paper, NOT_AVAILABLE, DASH]
    delta = ours.mean - cell.paper[m] if cell.paper else None
    return [paper, fmt_ci(ours, decimals), fmt_delta(delta, decimals)]


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
        + [t.cells[(row, g.name)].count]
        for row in t.rows
    ]


#: The subject section's columns: metric key of metrics.json → header.
SUBJECT_COLUMNS: dict[str, str] = {
    "psnr_subject": "subject PSNR↑", "ssim_subject": "subject SSIM↑",
    "gain_psnr": "gain over empty (full frame)", "gain_psnr_subject": "gain over empty (subject)"}


def _subject_rows(t: BuiltTable, g: Group) -> list[list[str]]:
    rows = []
    for row in t.rows:
        cell = t.cells[(row, g.name)]
        stats = cell_stats(cell.runs, list(SUBJECT_COLUMNS)) if cell.runs else None
        if stats is None:
            shown = {"collapsed": COLLAPSED, "failed": FAILED}.get(cell.status, DASH)
            rows.append([row] + [shown] * len(SUBJECT_COLUMNS) + [cell.count])
            continue
        rows.append([row] + [fmt_ci(v, t.paper.decimals) if v is not None else DASH
                             for v in stats] + [cell.count])
    return rows


def to_markdown(t: BuiltTable) -> str:
    """The table as Markdown: one sub-table per column group, the subject sections, then
    the footnotes."""
    intro = (f"_{t.paper.caption}_ Columns: paper, ours (mean ± 95 % interval over the "
             "seeds scored), Δ = ours − paper, n = seeds scored / run.")
    out = [f"## {t.paper.title}", "", intro, ""]
    for g in t.groups:
        header = [t.paper.row_header] + [
            f"{METRIC_LABELS[m]} {what}"
            for m in t.paper.metrics
            for what in ("paper", "ours", "Δ")
        ] + ["n"]
        out += [f"### {_group_title(t, g)}", "", markdown_table(header, _group_rows(t, g)), ""]
    for g in t.groups:
        runs = [r for row in t.rows for r in t.cells[(row, g.name)].runs]
        if g.scene is None or not any(r.metric("psnr_subject") is not None for r in runs):
            continue
        header = [t.paper.row_header, *SUBJECT_COLUMNS.values(), "n"]
        out += [f"### Subject region — `{g.scene}` (ours only; masks of the held-out frames)",
                "", markdown_table(header, _subject_rows(t, g)), ""]
    out += [f"- {n}" for n in t.notes]
    return "\n".join(out).rstrip() + "\n"


def to_latex(t: BuiltTable) -> str:
    """The table as LaTeX (``booktabs``): one tabular block per column group."""
    k = len(t.paper.metrics)
    spec = "l" + " rrr" * k + " l"
    lines = [r"% requires \usepackage{booktabs}", r"\begin{table}[t]", r"\centering", r"\small"]
    for g in t.groups:
        lines += [rf"\begin{{tabular}}{{{spec}}}", r"\toprule"]
        lines.append(rf"\multicolumn{{{2 + 3 * k}}}{{c}}{{{latex_text(_group_title(t, g))}}} \\")
        spans = [
            rf"\multicolumn{{3}}{{c}}{{{latex_text(METRIC_LABELS[m])}}}" for m in t.paper.metrics
        ]
        lines.append(" & ".join(["", *spans, ""]) + r" \\")
        lines.append(" ".join(rf"\cmidrule(lr){{{2 + 3 * i}-{4 + 3 * i}}}" for i in range(k)))
        sub = [latex_text(t.paper.row_header)] + ["paper", "ours", r"$\Delta$"] * k + ["n"]
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
