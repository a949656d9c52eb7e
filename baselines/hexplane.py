"""HexPlane: six feature planes, three spatial and three space-time.

Planes ``P_xy, P_xz, P_yz`` (spatial) and ``P_zt, P_yt, P_xt`` (space-time), each
``[2R, R_a, R_b]``. Complementary pairs multiply,

.. math:: g_p(\\mathbf{c}) = P_{S_p}(c_{S_p}) \\odot P_{T_p}(c_{T_p}),\\qquad
          (S_p, T_p) \\in \\{(xy, zt), (xz, yt), (yz, xt)\\},

giving ``2R`` components per pair: raw density ``sum_p sum_{r<R} g_{p,r}`` and the
appearance components of the three pairs concatenated (``3R``) and decoded to colour
by a linear basis (or a small MLP). Density ``trunc_exp``, colour ``sigmoid``
(:mod:`baselines.heads`). Growth as TensoRF-CP (:class:`~baselines.schedules.GridGrowth`).
Spatial planes start as N(0, init_scale^2), time planes as 1 + N(0, 1e-2).

:meth:`HexPlaneField.regularization` is total variation with the time direction weighted
on its own (HexPlane's spatial TV plus a stronger temporal smoothness):
``tv_space * [sum_spatial TV(P) + sum_spacetime TV_space(P)] + tv_time * sum_spacetime TV_t(P)``,
where ``TV_space`` / ``TV_t`` difference a space-time plane along its spatial / its time axis.
Paper scale: 500^3 x 24, rank 8, lr 1e-2.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import torch
from torch import Tensor

from baselines.factorised import FactorisedField
from baselines.grids import total_variation
from baselines.heads import DensityActivation

#: (spatial plane, complementary space-time plane), axes 0..3 = (x, y, z, t).
PAIRS: tuple[tuple[tuple[int, int], tuple[int, int]], ...] = (
    ((0, 1), (2, 3)), ((0, 2), (1, 3)), ((1, 2), (0, 3)))


class HexPlaneField(FactorisedField):
    """HexPlane field; see the module docstring for the maths.

    >>> f = HexPlaneField(rank=2, resolution_init=(4, 4, 4, 4), resolution_final=(8, 8, 8, 6))
    >>> sigma, rgb = f(torch.zeros(5, 3), torch.full((5, 1), 0.5))
    >>> tuple(sigma.shape), tuple(rgb.shape), len(f.grids.factors)
    ((5,), (5, 3), 6)
    """

    def __init__(self, rank: int = 8, resolution_init: Sequence[int] = (16, 16, 16, 16),
                 resolution_final: Sequence[int] = (64, 64, 64, 24), n_growth: int = 5,
                 growth_until: float = 0.2, init_scale: float = 0.1,
                 tv_space: float = 1e-4, tv_time: float = 1e-3,
                 decoder: Literal["linear", "mlp"] = "linear", decoder_hidden: int = 64,
                 decoder_lr_scale: float = 0.1, density_shift: float = 0.0,
                 density_activation: DensityActivation = "trunc_exp", bound: float = 1.0,
                 seed: int = 0):
        axes = [s for s, _ in PAIRS] + [t for _, t in PAIRS]
        init = [(0.0, init_scale)] * 3 + [(1.0, 1e-2)] * 3
        super().__init__(axes, init, rank, 3 * rank, resolution_init, resolution_final,
                         n_growth, growth_until, decoder, decoder_hidden, decoder_lr_scale,
                         density_shift, density_activation, bound, seed)
        self.tv_space = tv_space
        self.tv_time = tv_time

    def components(self, samples: list[Tensor]) -> tuple[Tensor, Tensor]:
        """Pair products ``g_p = P_S * P_T`` (``[2R, N]``) -> (density, appearance) ``[3R, N]``."""
        r = self.rank
        g = [samples[p] * samples[p + 3] for p in range(3)]
        return torch.cat([x[:r] for x in g]), torch.cat([x[r:] for x in g])

    def regularization(self) -> Tensor:
        """TV along space at ``tv_space``, along time at ``tv_time`` (module docstring).

        Space-time planes are ``[2R, R_space, R_t]``: dim 1 is space, dim 2 is time.
        """
        f = self.grids.factors
        space = sum(total_variation(f[p]) for p in range(3))
        space = space + sum(total_variation(f[p + 3], dims=(1,)) for p in range(3))
        time = sum(total_variation(f[p + 3], dims=(2,)) for p in range(3))
        return self.tv_space * space + self.tv_time * time
