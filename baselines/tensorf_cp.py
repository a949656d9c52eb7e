"""TensoRF-CP extended to space-time: rank-R vectors along x, y, z and t.

Each input axis ``a`` has a line ``v_a [F·R, N_a]``; with ``c`` the coordinates
normalised to the clipping cylinder's box (:mod:`baselines.factorised`) the rank
components are

.. math:: g_{f,r}(\\mathbf{c}) = v_{x,fr}(c_x)\\, v_{y,fr}(c_y)\\, v_{z,fr}(c_z)\\,
          v_{t,fr}(c_t),

summed over ``r`` into the raw density and the three raw colours (a rank-R CP
decomposition of the 5-way tensor ``(x, y, z, t, feature)``; no decoder). The lines are
sampled with ``align_corners=False`` and zero padding, as the authors' ``sample_vec``.

The grid grows geometrically in ``n_stages`` stages over the first ``growth_steps``
steps: the authors' public config is rank 50, 16 → 500 in space and 16 → 24 in time, 10
stages over 10⁴ steps (the supplementary states rank 8 over 2·10³ of 10⁴ steps:
``model.rank=8 model.growth_steps=2000``).
"""

from __future__ import annotations

from collections.abc import Sequence

from torch import Tensor

from baselines.factorised import FactorisedField
from baselines.schedules import GrowthPlan
from eventrecon.kernels import factor_grids


class TensoRFCPField(FactorisedField):
    """TensoRF-CP 4D field; see the module docstring for the maths.

    Args:
        rank: components ``R`` per output feature.
        resolution_init, resolution_final: vertices per axis ``(x, y, z, t)``.
        n_stages, growth_steps: the growth (:class:`~baselines.schedules.GrowthPlan`).
        init_gain: lines start as ``N(0, (init_gain / R)²)``.
        seed: initialisation seed.
        implementation: the rank sum's (:mod:`eventrecon.kernels`).

    >>> import torch
    >>> f = TensoRFCPField(rank=2, resolution_init=(4, 4, 4, 4), resolution_final=(8, 8, 8, 6))
    >>> sigma, rgb = f(torch.zeros(5, 3), torch.full((5, 1), 0.5))
    >>> tuple(sigma.shape), tuple(rgb.shape), [tuple(p.shape) for p in f.grids.factors]
    ((5,), (5, 3), [(8, 4), (8, 4), (8, 4), (8, 4)])
    """

    def __init__(self, rank: int = 50, resolution_init: Sequence[int] = (16, 16, 16, 16),
                 resolution_final: Sequence[int] = (500, 500, 500, 24), n_stages: int = 10,
                 growth_steps: int = 10000, init_gain: float = 1.0, seed: int = 0,
                 implementation: str = "auto"):
        plan = GrowthPlan(tuple(resolution_init), tuple(resolution_final), n_stages,
                          growth_steps)
        super().__init__([(0,), (1,), (2,), (3,)], [False] * 4, rank, plan, init_gain, seed,
                         implementation)

    def shapes(self, resolution: Sequence[int]) -> list[tuple[int, ...]]:
        """One line per axis: ``[(N_x,), (N_y,), (N_z,), (N_t,)]``."""
        return [(int(r),) for r in resolution]

    @property
    def resolution(self) -> tuple[int, ...]:
        return tuple(s[0] for s in self.grids.shapes)

    def combine(self, samples: list[Tensor]) -> Tensor:
        """``v_x · v_y · v_z · v_t`` per channel."""
        return samples[0] * samples[1] * samples[2] * samples[3]

    def kernel_unsupported(self, factors: list[Tensor], coords: Tensor) -> str | None:
        return factor_grids.cp_unsupported(factors, coords, self.grids.align_corners)

    def kernel(self, factors: list[Tensor], coords: Tensor) -> Tensor:
        """One compiled pass over the four lines (:func:`~eventrecon.kernels.factor_grids.
        cp_rank_sum`)."""
        return factor_grids.cp_rank_sum(factors, coords, self.grids.align_corners,
                                        self.grids.padding, self.rank)
