"""Accuracy vs wall-clock time, per backbone: a PNG and a Markdown table.

Each run's ``curve.csv`` holds held-out evaluations ``(wall_s, step, psnr, ssim, lpips,
kind)`` on a fixed step schedule: ``cheap`` rows (every ``trainer.curve_every`` steps)
score ``trainer.curve_pixels`` fixed random pixels of every held-out view at three
ground-truth times of the segment, ``full`` rows (every ``trainer.eval_every`` steps and
at the end) the whole images at those times. Both estimate the same held-out PSNR, so
time-to-level uses every row: the first logged wall-clock time with ``PSNR ≥ level`` —
no interpolation, so it is an upper bound on the true crossing time within one
evaluation interval. Wall-clock is training time only (evaluation time is excluded).

>>> time_to_level(np.array([1.0, 2.0, 3.0]), np.array([14.0, 21.0, 26.0]), 20.0)
2.0
>>> time_to_level(np.array([1.0, 2.0]), np.array([14.0, 18.0]), 20.0) is None
True
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eventrecon.report.budgets import budget_markdown
from eventrecon.report.format import DASH, fmt, markdown_table
from eventrecon.report.runs import MODELS, Run, run_curve

log = logging.getLogger(__name__)

#: PSNR levels (dB) of the time-to-quality table.
DEFAULT_LEVELS: tuple[float, ...] = (15.0, 20.0, 25.0, 30.0)
_METRICS = (("psnr", "PSNR [dB] ↑"), ("ssim", "SSIM ↑"), ("lpips", "LPIPS-Alex ↓"))


def trailing_median(psnr: np.ndarray, window: int = 5) -> np.ndarray:
    """``[T]``: at point ``i`` the median of ``psnr[max(0, i − window + 1) … i]``, a curve's
    level from the points logged so far (``window`` 1: the points themselves). Held-out
    curve points of one run scatter by ~0.5 dB from one to the next; a median of a few
    is what a single point is not, steady.

    >>> trailing_median(np.array([20.0, 24.0, 21.0, 25.0, 22.0]), 3).tolist()
    [20.0, 22.0, 21.0, 24.0, 22.0]
    """
    p = np.asarray(psnr, float)
    return np.array([np.median(p[max(0, i - window + 1):i + 1]) for i in range(p.size)])


def time_to_level(wall_s: np.ndarray, psnr: np.ndarray, level: float,
                  window: int = 1) -> float | None:
    """First ``wall_s[i]`` (in time order) at which the :func:`trailing_median` of the last
    ``window`` PSNRs reaches ``level`` (``window`` 1: ``psnr[i] ≥ level`` itself); ``None``
    if never.

    ``wall_s, psnr``: ``[T]``; NaN PSNRs are ignored.

    >>> time_to_level(np.array([1.0, 2.0, 3.0, 4.0]), np.array([20.0, 26.0, 23.0, 25.0]),
    ...               24.0, window=3)
    4.0
    """
    order = np.argsort(wall_s, kind="stable")
    w, p = np.asarray(wall_s, float)[order], np.asarray(psnr, float)[order]
    keep = np.isfinite(p)
    hit = np.flatnonzero(trailing_median(p[keep], window) >= level)
    return float(w[keep][hit[0]]) if hit.size else None


@dataclass
class CurveSummary:
    """Time-to-quality figures of one run (``times[level]`` in seconds or ``None``)."""

    run: Run
    kind: str  # "full", "cheap" or "none": which curve rows the figures use
    times: dict[float, float | None]
    best_psnr: float | None


def summarize(run: Run, levels: Sequence[float] = DEFAULT_LEVELS) -> CurveSummary:
    """Time to each PSNR level and the best logged PSNR of ``run``'s curve (all rows)."""
    c = run_curve(run)
    kinds = sorted(set(c["kind"].tolist()))
    kind = "+".join(kinds) if kinds else "none"
    w, p = c["wall_s"], c["psnr"]
    finite = p[np.isfinite(p)]
    return CurveSummary(
        run=run,
        kind=kind,
        times={lv: time_to_level(w, p, lv) for lv in levels},
        best_psnr=float(finite.max()) if finite.size else None,
    )


def backbone_runs(runs: Sequence[Run], experiment: str | None = "table3") -> list[Run]:
    """The runs of the backbone comparison: the ``loss=full`` runs of ``experiment`` (the
    Tab. 3 sweep: its zoo rows and the full model). Without any, those of the experiment
    (or of the untagged single runs) that has the most backbones, so that sweeps over
    frame rates or views are not mixed into one plot; ``experiment=None`` takes that
    choice directly."""
    full = [r for r in runs if r.loss == "full"]
    mine = [r for r in full if experiment is not None and r.experiment == experiment]
    if mine:
        return mine
    groups: dict[str | None, list[Run]] = {}
    for r in full:
        groups.setdefault(r.experiment, []).append(r)
    if not groups:
        return []
    best = max(groups, key=lambda e: (len({r.model for r in groups[e]}), len(groups[e])))
    return groups[best]
def _model_rank(model: str) -> int:
    return MODELS.index(model) if model in MODELS else len(MODELS)


def accuracy_table(
    summaries: Sequence[CurveSummary], levels: Sequence[float] = DEFAULT_LEVELS
) -> str:
    """Markdown: per run, time to each PSNR level, best / final PSNR, s/it, peak memory."""
    header = ["Backbone", "Scene", "Loss", "seed", "eval"]
    header += [f"t → {lv:g} dB [s]" for lv in levels]
    header += ["best PSNR", "final PSNR", "s/it", "peak mem [MB]", "status"]
    rows = []
    ordered = sorted(
        summaries, key=lambda s: (_model_rank(s.run.model), s.run.model, s.run.scene, s.run.loss)
    )
    for s in ordered:
        r = s.run
        rows.append(
            [r.model, r.scene, r.loss, str(r.record.get("seed", DASH)), s.kind]
            + [fmt(s.times[lv], 1) for lv in levels]
            + [
                fmt(s.best_psnr, 2),
                fmt(r.metric("psnr"), 2) if r.ok else r.status,
                fmt(r.number("sec_per_it"), 4),
                fmt(r.number("peak_mem_mb"), 0),
                r.status,
            ]
        )
    notes = [
        "",
        "- t → L: first logged wall-clock training time with held-out PSNR ≥ L (—: never "
        "reached), over every evaluation of the curve (eval: cheap = fixed random pixels, "
        "full = whole images, of every held-out view at three times).",
        "- best PSNR: maximum over the curve; final PSNR: metrics.json at the end of training "
        "(\"collapsed\": the run renders the empty field, no score).",
    ]
    return markdown_table(header, rows) + "\n" + "\n".join(notes) + "\n"


def plot_accuracy_vs_time(runs: Sequence[Run], path: str | Path, loss: str | None = "full") -> Path:
    """PSNR (and SSIM, LPIPS where logged) against wall-clock seconds: one column of
    panels per scene, one row per metric, colour = backbone, one thin line per run (its
    seeds side by side), markers on the ``full`` evaluations (the only ones with SSIM and
    LPIPS). The legend names the backbones once.

    Only runs with ``loss`` (the backbone comparison) are drawn when there are any;
    ``loss=None`` draws every run. Collapsed and failed runs are not drawn as curves: the
    figure names them instead ("not drawn — ..."). Writes a PNG (Agg backend) and
    returns its path.
    """
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.ticker import NullFormatter

    chosen = [r for r in runs if loss is None or r.loss == loss] or list(runs)
    not_drawn = [r for r in chosen if not r.ok]
    curves = [(r, run_curve(r)) for r in chosen if r.ok]
    curves = [(r, c) for r, c in curves if len(c["wall_s"])]
    shown = [(k, lab) for k, lab in _METRICS if any(np.isfinite(c[k]).any() for _, c in curves)]
    shown = shown or list(_METRICS[:1])
    scenes = sorted({r.scene for r, _ in curves}) or ["—"]
    fig, axes = plt.subplots(len(shown), len(scenes), squeeze=False, sharex=True,
                             sharey="row", figsize=(2.9 * len(scenes) + 0.6,
                                                    2.5 * len(shown) + 1.0))
    models = sorted({r.model for r, _ in curves}, key=lambda m: (_model_rank(m), m))
    colours = {m: plt.get_cmap("tab10")(i % 10) for i, m in enumerate(models)}
    tmax = max((float(np.nanmax(c["wall_s"])) for _, c in curves), default=1.0)
    positive = [c["wall_s"][c["wall_s"] > 0] for _, c in curves]
    tmin = min((float(p.min()) for p in positive if p.size), default=1.0)
    for (key, label), row in zip(shown, axes):
        for r, c in curves:
            ax, col = row[scenes.index(r.scene)], colours[r.model]
            has, full = np.isfinite(c[key]), c["kind"] == "full"
            ax.plot(c["wall_s"][has], c[key][has], "-", color=col, lw=1.0, alpha=0.7)
            ax.plot(c["wall_s"][full & has], c[key][full & has], "o", color=col, ms=3)
        row[0].set_ylabel(label)
    for scene, ax in zip(scenes, axes[0]):
        ax.set_title(scene, fontsize=10)
    for ax in axes.flat:
        if tmax / max(tmin, 1e-9) > 100:
            ax.set_xscale("log")
            ax.xaxis.set_minor_formatter(NullFormatter())  # decades only: no overlapping labels
        ax.grid(alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("training time [s]")
    if not curves:
        axes[0][0].text(0.5, 0.5, "no curve.csv found", ha="center", transform=axes[0][0].transAxes)
    if models:
        fig.legend([Line2D([], [], color=colours[m], marker="o", ms=3) for m in models], models,
                   loc="upper right", ncol=len(models), fontsize=8, frameon=False)
    if not_drawn:
        names = sorted({f"{r.model}/{r.scene} seed {r.record.get('seed')}: {r.status}"
                        for r in not_drawn})
        fig.text(0.01, 0.005, "not drawn — " + "; ".join(names[:6])
                 + (f"; +{len(names) - 6} more" if len(names) > 6 else ""), fontsize=7,
                 color="0.3")
    fig.suptitle("Held-out quality vs wall-clock training time (markers: full evaluations)",
                 x=0.01, ha="left", fontsize=10)
    fig.tight_layout(rect=(0, 0.02, 1, 0.97))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_accuracy_vs_time(
    runs: Sequence[Run], out: str | Path, levels: Sequence[float] = DEFAULT_LEVELS,
    experiment: str | None = "table3",
) -> list[Path]:
    """Write ``accuracy_vs_time.png`` and ``accuracy_vs_time.md`` into ``out`` for the
    backbone comparison (:func:`backbone_runs` of ``experiment``)."""
    out = Path(out)
    chosen = backbone_runs(runs, experiment)
    png = plot_accuracy_vs_time(chosen, out / "accuracy_vs_time.png")
    md = out / "accuracy_vs_time.md"
    which = sorted({str(r.experiment) for r in chosen})
    title = ("## Accuracy vs wall-clock time\n\n"
             f"Runs: `loss=full` of {', '.join(which) or 'none'} ({len(chosen)} runs).\n\n"
             "![accuracy vs time](accuracy_vs_time.png)\n\n")
    budgets = budget_markdown(chosen)
    md.write_text(title + (budgets + "\n### Per run\n\n" if budgets else "")
                  + accuracy_table([summarize(r, levels) for r in chosen], levels))
    return [png, md]
