"""Common base of the factorised backbones (TensoRF-CP 4D, HexPlane).

A factorised field holds :class:`~baselines.grids.FactorGrids` whose channels are split
into ``R`` density and ``R`` appearance components, a :class:`~baselines.heads.FactorDecoder`
and a :class:`~baselines.schedules.GrowthPlan`. Subclasses only say which axes the
factors span and how factor samples combine into components (:meth:`components`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import torch
from torch import Tensor

from baselines.grids import FactorGrids, normalize_xyzt
from baselines.heads import DensityActivation, FactorDecoder
from baselines.schedules import GridGrowth, GrowthPlan
from eventrecon.errors import InputError
from eventrecon.fields.base import Field


class FactorisedField(Field):
    """Field ``(xyz, t) -> (sigma, rgb)`` from products of dense factor grids.

    Args:
        axes: input axes spanned by each factor (see :class:`FactorGrids`).
        init: ``(mean, std)`` of each factor's Gaussian initialisation.
        rank: components ``R`` per group; factors have ``2R`` channels (density, appearance).
        app_dim: appearance features reaching the decoder (``R`` times a subclass factor).
        resolution_init, resolution_final: vertices per axis ``(x, y, z, t)``.
        n_growth: number of upsamplings (0: start at the final resolution).
        growth_until: fraction of the run by which growth ends.
        decoder, decoder_hidden, density_shift, density_activation: see :class:`FactorDecoder`.
        decoder_lr_scale: the decoder's learning rate is ``lr * decoder_lr_scale``.
        bound: world box half-size mapped to ``[-1, 1]``.
        seed: initialisation seed.
    """

    def __init__(self, axes: Sequence[Sequence[int]], init: Sequence[tuple[float, float]],
                 rank: int, app_dim: int, resolution_init: Sequence[int],
                 resolution_final: Sequence[int], n_growth: int, growth_until: float,
                 decoder: Literal["linear", "mlp"], decoder_hidden: int,
                 decoder_lr_scale: float, density_shift: float,
                 density_activation: DensityActivation, bound: float, seed: int):
        super().__init__()
        for name, res in (("resolution_init", resolution_init),
                          ("resolution_final", resolution_final)):
            if len(res) != 4 or min(res) < 2:
                raise InputError("conf/model", name, "4 resolutions (x, y, z, t), each >= 2",
                                 list(res))
        if rank < 1 or n_growth < 0 or not 0.0 < growth_until <= 1.0:
            raise InputError("conf/model", "rank/n_growth/growth_until",
                             "rank >= 1, n_growth >= 0, 0 < growth_until <= 1",
                             (rank, n_growth, growth_until))
        self.rank = rank
        self.bound = bound
        self.decoder_lr_scale = decoder_lr_scale
        self.plan = GrowthPlan(tuple(resolution_init), tuple(resolution_final), n_growth,
                               growth_until)
        gen = torch.Generator().manual_seed(seed)
        self.grids = FactorGrids(axes, 2 * rank, self.plan.initial, init, gen)
        self.decoder = FactorDecoder(app_dim, decoder, decoder_hidden, density_shift,
                                     density_activation)

    @property
    def resolution(self) -> tuple[int, ...]:
        """Current vertices per axis ``(x, y, z, t)``."""
        return self.grids.resolution

    def upsample(self, resolution: Sequence[int]) -> None:
        """Grow every factor to ``resolution`` (new Parameters; rebuild the optimiser)."""
        self.grids.upsample(resolution)

    def components(self, samples: list[Tensor]) -> tuple[Tensor, Tensor]:
        """Combine factor samples ``[2R, N]`` into ``(density [R_d, N], app [app_dim, N])``."""
        raise NotImplementedError

    def forward(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        """``xyz [N, 3], t [N, 1] -> (sigma [N], rgb [N, 3])``."""
        coords = normalize_xyzt(xyz, t, self.bound)
        return self.decoder(*self.components(self.grids(coords)))

    def param_groups(self, lr: float) -> list[dict[str, Any]]:
        """Grids at ``lr``, decoder at ``lr * decoder_lr_scale``."""
        return [
            {"params": list(self.grids.parameters()), "lr": lr, "name": "grids"},
            {"params": list(self.decoder.parameters()), "lr": lr * self.decoder_lr_scale,
             "name": "decoder"},
        ]

    def callbacks(self) -> list[Any]:
        """Grid growth (upsampling + optimiser rebuild) when ``n_growth > 0``."""
        return [GridGrowth(self, self.plan)] if self.plan.n_growth > 0 else []
