"""Quality at equal training time, per backbone: what accuracy costs in wall-clock.

A run's held-out PSNR *within a budget* of ``B`` seconds is the last evaluation of its
``curve.csv`` logged at a training wall-clock time ``≤ B`` -- the score it would keep if
training stopped there (a run that finished sooner keeps its last evaluation; one whose
first evaluation comes after ``B`` has none). Curves log training time only, evaluation
excluded.

Per backbone the report gives the mean over (scene, seed) of that PSNR at each budget
with its 95 % interval, and the paired difference to the reference backbone (the
paper's NeRF MLP): both runs of a pair share the scene, the seed and the method version
(:func:`~eventrecon.report.pairs.paired`), so the spread of the scenes does not hide a
difference that every scene shows. The last column compares the runs at the end of
training (``metrics.json``, equal steps). Collapsed and failed runs are not scored and
drop their pairs.

Wall-clock is what each job recorded: the sweeps run two one-thread jobs side by side,
and the jobs of one table may come from sessions on machines of different speed, so the
median seconds per step is printed beside each backbone.

>>> psnr_within(np.array([10.0, 20.0, 30.0]), np.array([18.0, 22.0, 21.0]), 25.0)
22.0
>>> psnr_within(np.array([10.0, 20.0]), np.array([18.0, 22.0]), 5.0) is None
True
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from eventrecon.report.format import DASH, fmt, markdown_table
from eventrecon.report.pairs import paired
from eventrecon.report.runs import MODELS, Run, run_curve
from eventrecon.report.stats import MeanCI, mean_ci

__all__ = ["DEFAULT_BUDGETS", "psnr_within", "machines_cell", "budget_markdown"]

#: Training wall-clock budgets (seconds) of the per-backbone comparison.
DEFAULT_BUDGETS: tuple[float, ...] = (60.0, 120.0, 180.0)


def psnr_within(wall_s: np.ndarray, psnr: np.ndarray, budget: float) -> float | None:
    """The last finite ``psnr[i]`` (in time order) with ``wall_s[i] ≤ budget``; ``None``
    if there is none. ``wall_s, psnr``: ``[T]``."""
    order = np.argsort(wall_s, kind="stable")
    w, p = np.asarray(wall_s, float)[order], np.asarray(psnr, float)[order]
    hit = np.flatnonzero((w <= budget) & np.isfinite(p))
    return float(p[hit[-1]]) if hit.size else None


def _within(budget: float, curves: dict[Path, dict[str, np.ndarray]]):
    """``run → PSNR within budget`` (:func:`psnr_within` on the run's curve, read once
    into ``curves`` by path)."""
    def value(run: Run) -> float | None:
        c = curves.get(run.path)
        if c is None:
            c = curves[run.path] = run_curve(run)
        return psnr_within(c["wall_s"], c["psnr"], budget)
    return value


def _cell(m: MeanCI | None, signed: bool = False) -> str:
    """``mean ± half (n)``; bold when a difference's interval excludes zero."""
    if m is None or m.n == 0:
        return DASH
    text = f"{m.mean:+.2f}" if signed else f"{m.mean:.2f}"
    text += f" ± {m.half:.2f}" if m.half is not None else ""
    if signed and m.excludes_zero:
        text = f"**{text}**"
    return f"{text} ({m.n})"


def machines_cell(runs: Sequence[Run]) -> str:
    """The machines ``runs`` trained on (``machine`` in their records), each with its run
    count, most runs first; records that do not name one count as ``not recorded``.

    A wall-clock comparison between backbones is like for like only where this cell
    names one machine for both."""
    counts = Counter(str(r.record.get("machine") or "not recorded") for r in runs)
    return "; ".join(f"{name} ({n})" for name, n in
                     sorted(counts.items(), key=lambda kv: (-kv[1], kv[0]))) or DASH


def budget_markdown(runs: Sequence[Run], budgets: Sequence[float] = DEFAULT_BUDGETS,
                    reference: str = "nerf") -> str:
    """Markdown: per backbone, held-out PSNR within each training budget and at the end
    (mean ± 95 % interval (n) over scene × seed), then its paired difference to
    ``reference`` (module docstring). Empty string without runs."""
    scored = [r for r in runs if r.ok]
    order = {m: i for i, m in enumerate(MODELS)}
    models = sorted({r.model for r in runs}, key=lambda m: (order.get(m, len(MODELS)), m))
    if not models:
        return ""
    curves: dict[Path, dict[str, np.ndarray]] = {}      # each curve.csv read once
    values = [*(_within(b, curves) for b in budgets), lambda r: r.metric("psnr")]
    heads = [f"{b:g} s" for b in budgets] + ["end of training"]     # the differences
    totals = [f"PSNR within {h}" for h in heads[:-1]] + ["PSNR, end of training"]
    rows, diffs = [], []
    for m in models:
        mine = [r for r in scored if r.model == m]
        spi = [v for r in mine if (v := r.number("sec_per_it")) is not None]
        rows.append([m, f"{len(mine)} / {sum(r.model == m for r in runs)}",
                     fmt(float(np.median(spi)) if spi else None, 3)]
                    + [_cell(mean_ci([v for r in mine if (v := f(r)) is not None]))
                       for f in values] + [machines_cell(mine)])
        if m != reference and reference in models:
            diffs.append([m] + [_cell(paired(runs, lambda r, m=m: r.model == m,
                                             lambda r: r.model == reference, f)[0], True)
                                for f in values])
    text = ("### Per backbone, at equal training time\n\n"
            + markdown_table(["backbone", "scored / runs", "median s/it"] + totals
                             + ["machines (scored runs)"], rows)
            + "\n")
    if diffs:
        text += ("\n" + markdown_table([f"backbone − {reference}"] + heads, diffs) + "\n")
    text += (
        "\n- PSNR within B: the last held-out evaluation logged by B seconds of training "
        "(the score the run would keep if stopped there), mean ± 95 % interval (n) over "
        "scene × seed; end of training: `metrics.json` (equal steps).\n"
        f"- backbone − {reference}: paired over (scene, seed) of one method version; bold: "
        "the interval excludes zero. Wall-clock is each job's own (two one-thread jobs side "
        "by side). A table's jobs may come from sessions on machines of different speed: "
        "its wall-clock columns compare backbones only where their machines (the CPU or "
        "GPU in each record; older records do not name it) are one; the end of training "
        "(equal steps) compares them on any.\n")
    return text
