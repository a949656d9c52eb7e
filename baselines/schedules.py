"""Backbone schedules as Lightning callbacks: grid growth and cylinder annealing.

Both are expressed as fractions of the run (``trainer.max_steps``, or the estimated
number of optimiser steps for epoch-based runs), so the same preset scales from a
300-step CPU run to the paper's 10^4-3*10^4 iterations. Both are *stateless*: the
target (resolution, clip scale) is a function of ``trainer.global_step``, so a run
resumed from a checkpoint continues the schedule exactly.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import lightning.pytorch as pl

from baselines.grids import geometric_resolutions

log = logging.getLogger(__name__)


def total_steps(trainer: pl.Trainer) -> int:
    """The run's number of optimiser steps: ``max_steps`` if set, else Lightning's estimate."""
    if trainer.max_steps is not None and trainer.max_steps > 0:
        return int(trainer.max_steps)
    return int(trainer.estimated_stepping_batches)


@dataclass(frozen=True)
class GrowthPlan:
    """Geometric growth of a grid from ``start`` to ``end`` in ``n_growth`` upsamplings.

    Upsampling ``k = 1..K`` happens at step ``s_k = round(k / K * until * total)``; after
    it the per-axis resolution is ``round(start * (end / start)^(k / K))``.

    >>> GrowthPlan((16, 16), (64, 24), 2, 0.5).resolution_at(50, 100)
    (64, 24)
    >>> GrowthPlan((16, 16), (64, 24), 2, 0.5).resolution_at(49, 100)
    (32, 20)
    """

    start: tuple[int, ...]
    end: tuple[int, ...]
    n_growth: int
    until: float

    def steps(self, total: int) -> list[int]:
        """Training steps at which the grid is upsampled.

        ``s_k = round(k / K · until · total)``, at most ``total − 1`` so that the final
        resolution is always reached (``until = 1`` grows until the last step).

        >>> GrowthPlan((16,), (64,), 2, 1.0).steps(100)
        [50, 99]
        """
        k_max = self.n_growth
        return [min(int(round(k / k_max * self.until * total)), max(total - 1, 0))
                for k in range(1, k_max + 1)]

    def resolution_at(self, step: int, total: int) -> tuple[int, ...]:
        """Resolution the grid must have when training step ``step`` starts."""
        k = sum(s <= step for s in self.steps(total))
        return geometric_resolutions(self.start, self.end, self.n_growth)[k]

    @property
    def initial(self) -> tuple[int, ...]:
        return tuple(self.start) if self.n_growth > 0 else tuple(self.end)


class Growable(Protocol):
    """What :class:`GridGrowth` needs from a field."""

    resolution: tuple[int, ...]

    def upsample(self, resolution: Sequence[int]) -> None: ...


class GridGrowth(pl.Callback):
    """Upsample a field's grids on schedule, then rebuild the optimiser.

    At the start of each training batch the target resolution is
    ``plan.resolution_at(global_step, total_steps)``; if the field differs it calls
    ``field.upsample(target)`` (new Parameters) and ``trainer.strategy.setup_optimizers``,
    which calls the module's ``configure_optimizers`` again so the optimiser holds the
    new parameters (Adam moments restart, as in TensoRF).

    Limitation: under DDP the wrapped model is not re-wrapped after growth.
    """

    def __init__(self, field: Growable, plan: GrowthPlan):
        super().__init__()
        self.field = field
        self.plan = plan

    def on_train_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule,
                             batch: Any, batch_idx: int) -> None:
        target = self.plan.resolution_at(trainer.global_step, total_steps(trainer))
        if tuple(target) != tuple(self.field.resolution):
            log.info("step %d: grid %s -> %s", trainer.global_step, self.field.resolution, target)
            self.field.upsample(target)
            trainer.strategy.setup_optimizers(trainer)


class CylinderAnneal(pl.Callback):
    """Anneal the clipping cylinder: ``renderer.clip_scale = min(1, step / (fraction * total))``.

    The paper grows the NGP cylinder radius from 0 to 100 % over the first 10^4 of
    3*10^4 iterations (``fraction = 1/3``); the renderer reads ``clip_scale``.
    """

    def __init__(self, fraction: float = 1.0 / 3.0):
        super().__init__()
        self.fraction = fraction

    def scale(self, step: int, total: int) -> float:
        """``min(1, step / (fraction * total))``; 1 when ``fraction <= 0``."""
        n = self.fraction * total
        return 1.0 if n <= 0 else min(1.0, step / n)

    def on_train_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule,
                             batch: Any, batch_idx: int) -> None:
        s = self.scale(trainer.global_step, total_steps(trainer))
        pl_module.renderer.clip_scale = s
        pl_module.log("clip_scale", s, on_step=True, on_epoch=False)
