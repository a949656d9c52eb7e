"""Backbone schedules as Lightning callbacks: grid growth and cylinder annealing.

Both are written in training steps, as the authors' code runs them (the growth over its
first ``steps`` steps, the NGP cylinder over the first 10⁴); a config may compress them
for short runs (``trainer.schedule=compressed``, see :mod:`eventrecon.config.resolvers`). Both are
*stateless*: the target (resolution, clip scale) is a function of
``trainer.global_step``, so a run resumed from a checkpoint continues the schedule
exactly.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import lightning.pytorch as pl

from baselines.grids import geometric_resolutions

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GrowthPlan:
    """Geometric growth of a grid from ``start`` to ``end`` in ``n_stages`` stages.

    Stage ``k`` (resolution ``geometric_resolutions(start, end, n_stages)[k]``) is used
    from step ``k · steps / n_stages``: the stage at step ``s`` is
    ``min(n_stages − 1, s · n_stages // steps)``, the authors' rule (their TensoRF-CP
    grows from 16 to 500 in 10 stages over 10⁴ steps). ``n_stages = 1`` or ``steps = 0``:
    the final resolution from the start.

    >>> plan = GrowthPlan((16, 16), (500, 24), 10, 10000)
    >>> plan.resolution_at(0), plan.resolution_at(999), plan.resolution_at(1000)
    ((16, 16), (16, 16), (23, 16))
    >>> plan.resolution_at(9000), plan.growth_steps()[:2]
    ((500, 24), [1000, 2000])
    """

    start: tuple[int, ...]
    end: tuple[int, ...]
    n_stages: int
    steps: int

    def stage_at(self, step: int) -> int:
        """Index of the stage used at training step ``step``."""
        if self.n_stages <= 1 or self.steps <= 0:
            return max(self.n_stages - 1, 0)
        return min(self.n_stages - 1, int(step) * self.n_stages // self.steps)

    def resolution_at(self, step: int) -> tuple[int, ...]:
        """Per-axis resolution the grid must have when training step ``step`` starts."""
        return geometric_resolutions(self.start, self.end, self.n_stages)[self.stage_at(step)]

    def growth_steps(self) -> list[int]:
        """Steps at which the resolution changes."""
        return [s for s in range(1, max(self.steps, 1) + 1)
                if self.stage_at(s) != self.stage_at(s - 1)]

    @property
    def initial(self) -> tuple[int, ...]:
        return self.resolution_at(0)


class Growable(Protocol):
    """What :class:`GridGrowth` needs from a field."""

    resolution: tuple[int, ...]

    def upsample(self, resolution: Sequence[int]) -> None: ...


class GridGrowth(pl.Callback):
    """Upsample a field's grids on schedule, then rebuild the optimiser.

    At the start of each training batch the target resolution is
    ``plan.resolution_at(global_step)``; if the field differs it calls
    ``field.upsample(target)`` (new Parameters) and ``trainer.strategy.setup_optimizers``,
    which calls the module's ``configure_optimizers`` again so the optimiser holds the
    new parameters (Adam moments restart; the authors' code activates a fresh parameter
    per stage, with fresh moments too).

    Limitation: under DDP the wrapped model is not re-wrapped after growth.
    """

    def __init__(self, field: Growable, plan: GrowthPlan):
        super().__init__()
        self.field = field
        self.plan = plan

    def on_train_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule,
                             batch: Any, batch_idx: int) -> None:
        target = self.plan.resolution_at(trainer.global_step)
        if tuple(target) != tuple(self.field.resolution):
            log.info("step %d: grid %s -> %s", trainer.global_step, self.field.resolution, target)
            self.field.upsample(target)
            trainer.strategy.setup_optimizers(trainer)


class CylinderAnneal(pl.Callback):
    """Anneal the clipping cylinder: ``renderer.clip_scale = min(1, step / steps)``.

    The NGP baseline grows the radius inside which density is kept from 0 to 100 % over
    the first 10⁴ steps (supplementary Sec. 10); as in the authors' code only the density
    is masked, the samples still span the whole cylinder (the renderer reads
    ``clip_scale`` in its density mask only).

    >>> CylinderAnneal(10000).scale(2500)
    0.25
    """

    def __init__(self, steps: int = 10000):
        super().__init__()
        self.steps = int(steps)

    def scale(self, step: int) -> float:
        """``min(1, step / steps)``; 1 when ``steps <= 0``."""
        return 1.0 if self.steps <= 0 else min(1.0, step / self.steps)

    def on_train_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule,
                             batch: Any, batch_idx: int) -> None:
        s = self.scale(trainer.global_step)
        pl_module.renderer.clip_scale = s
        pl_module.log("clip_scale", s, on_step=True, on_epoch=False)
