"""A table cell of our runs: one run per seed, their mean ± 95 % interval, and what the
runs changed from the paper's method (for the footnotes).

A cell keeps every seed's run (:func:`per_seed`: the newest method version, then ok before
collapsed before failed, then the newest); only ``ok`` runs are scored
(:func:`cell_stats`); :attr:`Cell.count` says how many of how many, and why the others
were not.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field

from eventrecon.report.format import DASH, fmt
from eventrecon.report.runs import Run
from eventrecon.report.stats import MeanCI, mean_ci
from eventrecon.results.records import METHOD_VERSIONS

__all__ = ["Cell", "per_seed", "cell_stats", "fmt_ci", "method_notes"]


@dataclass
class Cell:
    """Paper values, our runs (one per seed) and their mean ± interval per metric
    (``None`` entries = unavailable)."""

    paper: tuple[float, ...] | None
    runs: list[Run] = field(default_factory=list)
    ours: tuple[MeanCI | None, ...] | None = None

    @property
    def scored(self) -> list[Run]:
        return [r for r in self.runs if r.ok]

    @property
    def count(self) -> str:
        """``"2/3 (1 collapsed)"``: seeds scored of seeds run, and why the others were not."""
        if not self.runs:
            return DASH
        why = [f"{n} {s}" for s in ("collapsed", "failed")
               if (n := sum(r.status == s for r in self.runs))]
        return f"{len(self.scored)}/{len(self.runs)}" + (f" ({', '.join(why)})" if why else "")

    @property
    def status(self) -> str:
        """``ok`` (some seed scored), ``collapsed`` / ``failed`` (none did), or ``missing``."""
        if self.scored:
            return "ok"
        if any(r.status == "collapsed" for r in self.runs):
            return "collapsed"
        return "failed" if self.runs else "missing"


_STATUS_ORDER = {"ok": 2, "collapsed": 1, "failed": 0}


def _rank(r: Run) -> tuple:
    """The newest method version first, then ok > collapsed > failed, then the later file."""
    return r.version, _STATUS_ORDER.get(r.status, -1), r.mtime, str(r.path)


def per_seed(runs: Sequence[Run]) -> list[Run]:
    """One run per seed: the newest method version, then ok before collapsed before failed,
    then the newest file."""
    best: dict[object, Run] = {}
    for r in runs:
        key = r.record.get("seed")
        if key not in best or _rank(r) > _rank(best[key]):
            best[key] = r
    return [best[k] for k in sorted(best, key=str)]


def cell_stats(runs: Sequence[Run], metrics: Sequence[str]) -> tuple[MeanCI | None, ...] | None:
    """Per metric the mean ± interval over the scored runs (``None`` when none has it)."""
    scored = [r for r in runs if r.ok]
    if not scored:
        return None
    out = []
    for m in metrics:
        vals = [v for r in scored if (v := r.metric(m)) is not None]
        out.append(mean_ci(vals) if vals else None)
    return tuple(out)


def fmt_ci(v: MeanCI, decimals: int) -> str:
    """``30.000`` (one seed) or ``30.000 ± 0.210``."""
    return fmt(v.mean, decimals) + (f" ± {v.half:.{decimals}f}" if v.half is not None else "")


def _dataset_notes(runs: Sequence[Run]) -> list[str]:
    """A footnote per scene whose runs were trained on different datasets (records'
    ``data_id``: a changed scene spec gets a new one; records without it predate it)."""
    by_scene: dict[str, Counter] = {}
    for r in {r.path: r for r in runs}.values():
        by_scene.setdefault(r.scene, Counter())[r.record.get("data_id")] += 1
    notes = []
    for scene, ids in sorted(by_scene.items()):
        if len(ids) > 1:
            parts = [f"{n} on `{d}`" for d, n in sorted((d, n) for d, n in ids.items() if d)]
            if ids.get(None):
                parts.append(f"{ids[None]} unrecorded (made before records named their data)")
            notes.append(f"`{scene}` runs on several datasets (records' data_id): "
                         + "; ".join(parts) + ". Cells are not yet all re-run on one.")
    return notes


def method_notes(runs: Sequence[Run]) -> list[str]:
    """Footnotes naming what the runs changed from the paper's method (their records say)."""
    notes = []
    schedules = Counter(r.record.get("schedule") for r in runs if r.record.get("schedule"))
    if schedules.get("compressed"):
        notes.append("Warm-up schedules compressed to the same share of the run as in the "
                     "paper's 150k steps (trainer.schedule=compressed: band annealing, the NGP "
                     "cylinder, TensoRF-CP's growth); the sparsity ramp keeps its 30000 steps.")
    sizes = sorted({str(r.record.get("sizing")) for r in runs if r.record.get("sizing")})
    if sizes:
        notes.append("Backbones at their CPU sizes: " + ", ".join(f"`conf/sizing/{s}.yaml`"
                                                                  for s in sizes) + ".")
    skips = {r.record.get("skip") for r in runs if r.record.get("skip")}
    if "grid" in skips:
        notes.append("Samples in cells the occupancy grid marks empty are not evaluated "
                     "(render.skip=grid).")
    decays = sorted({float(r.record["lr_end_factor"]) for r in runs
                     if r.record.get("lr_end_factor") not in (None, 1.0)})
    if decays:
        starts = sorted({float(r.record.get("lr_decay_start") or 0.0) for r in runs
                         if r.record.get("lr_end_factor") not in (None, 1.0)})
        notes.append("Learning rate decayed exponentially to "
                     + ", ".join(f"{d:g}×" for d in decays)
                     + " of its start by the last step (trainer.lr_end_factor; the authors "
                       "keep it constant)"
                     + ("" if starts == [0.0] else ", after a constant lr for the first "
                        + ", ".join(f"{a:.0%}" for a in starts)
                        + " of the steps (trainer.lr_decay_start)")
                     + ".")
    precisions = Counter(r.record.get("precision") for r in runs if r.record.get("precision"))
    if precisions.get("bf16-mixed"):
        notes.append(f"bf16 autocast on the CPU in {precisions['bf16-mixed']} of "
                     f"{sum(precisions.values())} runs that name their precision (the authors: "
                     "fp16 AMP on GPUs; trainer.lightning.precision=auto takes it only for the "
                     "NeRF MLP on a CPU with native bf16).")
    warmups = sorted({int(r.record["lr_warmup"]) for r in runs if r.record.get("lr_warmup")})
    if warmups:
        notes.append("Learning rate warmed up linearly over the first "
                     + ", ".join(str(w) for w in warmups)
                     + " steps (trainer.lr_warmup: the authors' scheduler's it/4000, which "
                       "their runs switch off).")
    powers = sorted({float(r.record["betas_power"]) for r in runs
                     if r.record.get("betas_power") not in (None, 1.0)})
    if powers:
        notes.append("Adam's betas raised to the power " + ", ".join(f"{k:g}" for k in powers)
                     + " (model.optim.betas_power: at k× the authors' lr the moments then "
                       "forget over the same distance of the path).")
    versions = Counter(r.version for r in {r.path: r for r in runs}.values())
    if len(versions) > 1:
        notes.append("Runs of several method versions (records' method_version): " + "; ".join(
            f"{n} of version {v} ({METHOD_VERSIONS.get(v, 'unknown')})"
            for v, n in sorted(versions.items())) + ". Cells are not yet all re-run.")
    notes += _dataset_notes(runs)
    steps = sorted({int(r.record["max_steps"]) for r in runs if r.record.get("max_steps")})
    if steps:
        notes.append(f"Training steps per segment: {', '.join(map(str, steps))} "
                     "(the paper: 150000).")
    return notes
