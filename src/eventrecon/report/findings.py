"""The supplementary's qualitative claims, checked against our runs.

Each claim is decided from *paired* differences between two settings over the (scene,
seed) pairs where both runs were scored with the same method version (collapsed and
failed runs are left out and counted), with the 95 % interval of the mean difference
(:mod:`.stats`):

- **holds** when the interval lies on the claimed side of zero (for "barely matters":
  inside ``±tolerance``);
- **fails** when it lies on the other side (for "barely matters": entirely outside);
- **inconclusive** otherwise — the difference is within the noise of the seeds — and
  **untested** when the runs are missing.

The claims (supplementary Sec. 12–15 and the captions of Tab. 3–7):

1. the full model performs best on average over the synthetic scenes (Tab. 3);
2. removing L_event hurts on scenes with events (Tab. 3, every scene but the static
   control);
3. event decay improves SSIM and LPIPS on noisy real(-like) data (Tab. 4), decided on
   each Tab. 4 scene on its own (``rig_lowlight``, the noisier ``rig_noisy`` and
   ``rig_drift``, whose dense ON-biased noise is what decay removes);
4. SSIM and LPIPS favour the full model on the real(-like) scene (Tab. 4, ``rig_lowlight``);
5. more views help (Tab. 6 and 7: the most views against the fewest);
6. the RGB frame rate barely matters (Tab. 5: the highest against the lowest rate,
   within ±0.5 dB, the paper's own spread over 0.5–100 FPS being 0.4 dB);
7. the model does not diverge with three views (Tab. 6: above the empty field).

Beside each verdict: the paper's own difference for the same comparison (its cells for
the columns our scenes stand for) and how many (scene, seed) pairs it would take, at the
spread of ours, for the paper's difference to lie outside the noise
(:func:`.stats.pairs_to_resolve`) -- an inconclusive verdict with far fewer pairs than that
is a comparison too small to see the paper's effect, not evidence against it.

Beside the claims: the full model against each Tab. 3 row (:func:`row_differences`).
The pairing and the paper's side of each comparison are :mod:`.pairs`; collapsed cells
against the paper's are :mod:`.collapses`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from eventrecon.report.format import fmt, markdown_table
from eventrecon.report.pairs import against_paper, inside, needed_text, paired, paper_difference
from eventrecon.report.rows import method_row, setting_label
from eventrecon.report.runs import Run
from eventrecon.report.stats import MeanCI, mean_ci, pairs_to_resolve
from eventrecon.report.tables import REAL_SCENE

__all__ = ["Finding", "check_findings", "findings_markdown", "RowDifference",
           "row_differences", "row_differences_markdown", "paired", "paper_difference"]

#: ± dB within which a difference "barely matters" (claim 6).
FPS_TOLERANCE_DB = 0.5

_FPS_CLAIM = "RGB frame rate barely matters (Tab. 5)"


@dataclass
class Finding:
    """One claim, its verdict and the evidence."""

    claim: str
    verdict: str
    diff: MeanCI | None
    metric: str
    cells: str
    note: str = ""
    #: the paper's difference for the same comparison and metric (``None``: no such cells)
    paper: float | None = None
    #: pairs needed, at our spread, to resolve ``paper`` (for "barely matters": to fit the
    #: interval inside the tolerance); ``None`` where that cannot be said
    needed: int | None = None


def _beside_paper(f: Finding, runs: Sequence[Run], table: str, labels: tuple[str, str],
                  a: Callable[[Run], bool], b: Callable[[Run], bool]) -> Finding:
    """``f`` with the paper's difference for its comparison, the pairs that would
    resolve it at our spread and a note on any repeated paper cell behind it."""
    f.paper, f.needed, note = against_paper(f.diff, runs, table, labels, a, b,
                                            f.metric.lower())
    f.note = "; ".join(x for x in (f.note, note) if x)
    return f


def _verdict(d: MeanCI | None, sign: int = 1) -> str:
    """``holds`` if the interval lies on the ``sign`` side of zero, ``fails`` if on the
    other, ``inconclusive`` if it contains zero (or has one value), ``untested`` without."""
    if d is None or d.n == 0:
        return "untested"
    if d.half is None:
        return "inconclusive"
    low, high = (d.low, d.high) if sign > 0 else (-d.high, -d.low)
    return "holds" if low > 0 else "fails" if high < 0 else "inconclusive"


def _in(table: str, runs: Sequence[Run]) -> list[Run]:
    return [r for r in runs if r.experiment == table]


def _row(table: str, label: str) -> Callable[[Run], bool]:
    return lambda r: method_row(r, table) == label


def _views(n: int | None) -> Callable[[Run], bool]:
    return lambda r: r.loss == "full" and r.views == n


def _fps(f: float | None) -> Callable[[Run], bool]:
    return lambda r: r.loss == "full" and r.fps == f


def _moving(runs: Sequence[Run]) -> list[Run]:
    """The runs on scenes with motion (every scene but the static control)."""
    return [r for r in runs if "static" not in r.scene]


def _against_each(runs: Sequence[Run], table: str, full: str, metric: str = "psnr"
                  ) -> list[tuple[str, MeanCI | None, int]]:
    """``(row, full − row, runs not scored)`` for every other row of ``table`` in ``runs``,
    paired over (scene, seed) (:func:`paired`)."""
    labels = sorted({lab for r in runs if (lab := method_row(r, table)) and lab != full})
    return [(lab, *paired(runs, _row(table, full), _row(table, lab), metric))
            for lab in labels]


def _full_vs_each(runs: Sequence[Run], table: str, full: str, metric: str, sign: int,
                  claim: str) -> Finding:
    """The full row against every other row: holds if better than each, fails if some row
    is better; the evidence shown is the closest competitor, beside the paper's. A row
    with runs but no scored pair of one method version (a table partly re-run at a new
    version) keeps the claim from holding: it is inconclusive until that row has pairs."""
    each = _against_each(runs, table, full, metric)
    lost = sum(n_lost for _, _, n_lost in each)
    results = [(lab, d) for lab, d, _ in each if d is not None]
    if not results:
        return Finding(claim, "untested", None, metric.upper(), "", _lost(lost))
    verdicts = [_verdict(d, sign) for _, d in results]
    lab, d = min(results, key=lambda x: sign * x[1].mean)
    verdict = ("fails" if "fails" in verdicts else "holds" if all(v == "holds" for v in verdicts)
               else "inconclusive")
    unpaired = [row for row, d_row, _ in each if d_row is None]
    if unpaired and verdict == "holds":
        verdict = "inconclusive"
    note = "; ".join(x for x in (
        f"{len(unpaired)} row(s) without scored pairs of one method version" if unpaired else "",
        _lost(lost)) if x)
    f = Finding(claim, verdict, d, metric.upper(),
                f"`{full}` − `{lab}` (closest of {len(results)} rows)", note)
    return _beside_paper(f, runs, table, (full, lab), _row(table, full), _row(table, lab))


def check_findings(runs: Sequence[Run]) -> list[Finding]:
    """Every claim of the module docstring, decided from ``runs``."""
    out: list[Finding] = []
    t3, t4, t5, t6, t7 = (_in(f"table{k}", runs) for k in range(3, 8))

    out.append(_full_vs_each(t3, "table3", "Full Model", "psnr", +1,
                             "Full model best on average (Tab. 3)"))

    labels = ("Full Model", "w/o L_event")
    rows = (_row("table3", labels[0]), _row("table3", labels[1]))
    d, lost = paired(_moving(t3), *rows)
    out.append(_beside_paper(
        Finding("Removing L_event hurts on scenes with events (Tab. 3)", _verdict(d), d,
                "PSNR", "`Full Model` − `w/o L_event`, scenes with motion", _lost(lost)),
        _moving(t3), "table3", labels, *rows))

    out += _decay_findings(t4)

    real4 = [r for r in t4 if r.scene == REAL_SCENE]
    out.append(_full_vs_each(real4, "table4", "Our Full Model (Final)", "ssim", +1,
                             "SSIM favours the full model on the real-like scene (Tab. 4)"))

    for key, table, name in (("table7", t7, "Tab. 7"), ("table6", t6, "Tab. 6")):
        views = sorted({r.views for r in table if r.views is not None})
        if len(views) >= 2:
            ends = (_views(views[-1]), _views(views[0]))
            d, lost = paired(table, *ends)
            out.append(_beside_paper(
                Finding(f"More views help ({name})", _verdict(d), d, "PSNR",
                        f"{views[-1]} views − {views[0]} views", _lost(lost)),
                table, key, (setting_label(views[-1]), setting_label(views[0])), *ends))
        else:
            out.append(Finding(f"More views help ({name})", "untested", None, "PSNR", ""))

    rates = sorted({r.fps for r in t5 if r.fps is not None})
    if len(rates) >= 2:
        ends = (_fps(rates[-1]), _fps(rates[0]))
        d, lost = paired(t5, *ends)
        if d is None:
            v = "untested"
        elif d.half is not None and abs(d.low) <= FPS_TOLERANCE_DB \
                and abs(d.high) <= FPS_TOLERANCE_DB:
            v = "holds"
        elif d.half is not None and (d.low > FPS_TOLERANCE_DB or d.high < -FPS_TOLERANCE_DB):
            v = "fails"
        else:
            v = "inconclusive"
        f = Finding(_FPS_CLAIM, v, d, "PSNR",
                    f"{rates[-1]:g} − {rates[0]:g} FPS, within ±{FPS_TOLERANCE_DB} dB",
                    _lost(lost))
        f.paper = paper_difference(t5, "table5", (setting_label(rates[-1]),
                                                  setting_label(rates[0])), *ends, "psnr")
        if d is not None and abs(d.mean) < FPS_TOLERANCE_DB:   # the interval inside ±tol
            f.needed = pairs_to_resolve(d, FPS_TOLERANCE_DB - abs(d.mean))
        out.append(f)
    else:
        out.append(Finding(_FPS_CLAIM, "untested", None, "PSNR", ""))

    three = [r for r in t6 if r.views == 3 and r.loss == "full"]
    gains = [g for r in three if r.ok and (g := _gain(r)) is not None]
    d = mean_ci(gains) if gains else None
    lost = sum(not r.ok for r in three)
    out.append(Finding("No divergence with three views (Tab. 6)",
                       _verdict(d) if not lost else "fails", d, "PSNR gain over empty field",
                       "3 views", _lost(lost)))
    return out


def _decay_findings(t4: Sequence[Run]) -> list[Finding]:
    """Claim 3, decided on each Tab. 4 scene separately (the real-like scene and any noisier
    variant run with ``experiment=table4``): ``Full − w/o decay`` in SSIM, and in LPIPS
    where it was computed (lower is better there)."""
    full4, no_decay = _row("table4", "Our Full Model (Final)"), _row("table4", "w/o decay")
    claim = "Event decay improves SSIM/LPIPS on noisy real-like data (Tab. 4"
    scenes = sorted({r.scene for r in t4 if full4(r) or no_decay(r)},
                    key=lambda s: (s != REAL_SCENE, s))
    out = []
    for scene in scenes or [REAL_SCENE]:
        runs = [r for r in t4 if r.scene == scene]
        d_ssim, lost = paired(runs, full4, no_decay, "ssim")
        d_lpips, _ = paired(runs, full4, no_decay, "lpips")
        if d_lpips is None:
            v = _verdict(d_ssim)
            note = "LPIPS unavailable: SSIM only" if d_ssim is not None else ""
        else:
            verdicts = {_verdict(d_ssim), _verdict(d_lpips, -1)}
            v = ("fails" if "fails" in verdicts else "holds" if verdicts == {"holds"}
                 else "inconclusive")
            note = ""
        out.append(_beside_paper(
            Finding(f"{claim}, `{scene}`)", v, d_ssim, "SSIM", "`Full` − `w/o decay`",
                    "; ".join(x for x in (note, _lost(lost)) if x)),
            runs, "table4", ("Our Full Model (Final)", "w/o decay"), full4, no_decay))
    return out


@dataclass
class RowDifference:
    """``Full − row`` in PSNR over all Tab. 3 scenes and over the scenes with motion."""

    row: str
    all_scenes: MeanCI | None
    moving: MeanCI | None
    lost: int
    #: the paper's ``Full − row`` over the columns of the scenes in ``all_scenes``
    paper: float | None = None
    #: pairs that would resolve ``paper`` at the spread of ``all_scenes``
    needed: int | None = None
    #: a repeated paper cell behind ``paper``, and the paper's difference without it
    note: str = ""


def row_differences(runs: Sequence[Run], table: str = "table3",
                    full: str = "Full Model") -> list[RowDifference]:
    """The full row against every other row of ``table``, paired over (scene, seed) —
    the evidence behind claim 1, one line per row, the closest rows first."""
    t = _in(table, runs)
    moving = {lab: d for lab, d, _ in _against_each(_moving(t), table, full)}
    out = []
    for lab, d, lost in _against_each(t, table, full):
        paper, needed, note = against_paper(d, t, table, (full, lab), _row(table, full),
                                            _row(table, lab), "psnr")
        out.append(RowDifference(lab, d, moving.get(lab), lost, paper, needed, note))
    return sorted(out, key=lambda x: x.all_scenes.mean if x.all_scenes else float("inf"))


def row_differences_markdown(diffs: Sequence[RowDifference]) -> str:
    """:func:`row_differences` as a Markdown section ("" without runs)."""
    def cell(d: MeanCI | None) -> list[str]:
        if d is None:
            return ["—", "0"]
        text = f"{fmt(d.mean, 2)} ± {fmt(d.half, 2)}" if d.half else fmt(d.mean, 2)
        if d.half and (d.low > 0 or d.high < 0):
            text = f"**{text}**"
        return [text, str(d.n)]

    if not diffs:
        return ""
    rows = [[d.row, *cell(d.all_scenes), *cell(d.moving), str(d.lost), fmt(d.paper, 2),
             inside(d.paper, d.all_scenes), needed_text(d.needed, d.all_scenes)]
            for d in diffs]
    header = ["row", "Full − row, all scenes (dB)", "n", "Full − row, scenes with motion (dB)",
              "n", "runs not scored", "paper, same scenes (dB)", "paper inside ours",
              "pairs to resolve the paper's"]
    return ("## Tab. 3: the full model against each row\n\n" + markdown_table(header, rows)
            + "\n\n- PSNR, paired over (scene, seed), mean ± 95 % interval; bold: the interval "
              "excludes zero. Runs not scored (collapsed or failed) drop their pairs.\n"
              "- paper: its Full − row averaged over the columns our scenes stand for; pairs to "
              "resolve it: (scene, seed) pairs that, at the spread of ours (all scenes), give a "
              "95 % interval narrower than the paper's difference (\"met\": n has them); paper "
              "inside ours **no**: our runs rule the paper's difference out at this scale.\n"
            + "".join(f"- {d.row}: {d.note}.\n" for d in diffs if d.note))


def _gain(r: Run) -> float | None:
    p, e = r.metric("psnr"), r.metric("psnr_background")
    return None if p is None or e is None else p - e


def _lost(n: int) -> str:
    return f"{n} run(s) not scored (collapsed/failed)" if n else ""


def findings_markdown(findings: Sequence[Finding]) -> str:
    """The findings table as Markdown."""
    rows = []
    for f in findings:
        diff = (f"{fmt(f.diff.mean, 3)} ± {fmt(f.diff.half, 3)}" if f.diff and f.diff.half
                else fmt(f.diff.mean, 3) if f.diff else "—")
        rows.append([f.claim, f.verdict, f.metric, diff, str(f.diff.n if f.diff else 0),
                     fmt(f.paper, 3), inside(f.paper, f.diff),
                     needed_text(f.needed, f.diff), f.cells, f.note])
    header = ["claim (supplementary)", "verdict", "metric", "paired difference ± 95 %", "n",
              "paper", "paper inside ours", "pairs to resolve the paper's", "cells", "note"]
    return ("## The paper's claims at this scale\n\n" + markdown_table(header, rows) + "\n\n"
            "- holds / fails: the 95 % interval of the mean paired difference (over scene × "
            "seed) lies on the claimed / the other side of zero; inconclusive: it contains "
            "zero (the effect is within the spread over seeds); untested: no runs.\n"
            "- paper: the paper's difference for the same cells (the columns our scenes stand "
            "for); pairs to resolve it: how many (scene, seed) pairs, at the spread of ours, "
            "give a 95 % interval narrower than the paper's difference (for \"barely matters\": "
            "an interval inside the tolerance at our mean; \"met\": n has them). An "
            "inconclusive verdict with far fewer pairs is too small a comparison to see the "
            "paper's effect; paper inside ours **no**: our runs rule the paper's difference out "
            "at this scale.\n")
