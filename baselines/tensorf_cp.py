"""TensoRF-CP extended to space-time: rank-R vectors along x, y, z and t.

Each input axis ``a`` has a line ``v_a [2R, R_a]``; with ``c`` the normalised
coordinates (:func:`~baselines.grids.normalize_xyzt`) the components are

.. math:: f_r(\\mathbf{c}) = v_{x,r}(c_x)\\, v_{y,r}(c_y)\\, v_{z,r}(c_z)\\, v_{t,r}(c_t),
          \\qquad r = 1..2R,

the first ``R`` are density components (raw density ``sum_r f_r``: a rank-R CP
decomposition of the 4D density grid), the last ``R`` appearance components mapped to
colour by a linear basis ``B [3, R]`` (a rank-R CP of the 5-way tensor
``(x, y, z, t, channel)``; ``decoder="mlp"`` swaps in a small MLP). Density
``trunc_exp``, colour ``sigmoid`` (:mod:`baselines.heads`).

The grid grows geometrically from 16^4 to the final size in ``n_growth`` upsamplings
over the first ``growth_until`` of training (supplementary: 16^4 -> 500^3 x 24, 10 steps
over 2*10^3 of 10^4 iterations, rank 8; the authors' public config: rank 50).
Spatial lines start as N(0, init_scale^2), the time line as 1 + N(0, 1e-2), i.e. a static
scene that learns to move.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

from torch import Tensor

from baselines.factorised import FactorisedField
from baselines.heads import DensityActivation


class TensoRFCPField(FactorisedField):
    """TensoRF-CP 4D field; see the module docstring for the maths.

    >>> import torch
    >>> f = TensoRFCPField(rank=2, resolution_init=(4, 4, 4, 4), resolution_final=(8, 8, 8, 6))
    >>> sigma, rgb = f(torch.zeros(5, 3), torch.full((5, 1), 0.5))
    >>> tuple(sigma.shape), tuple(rgb.shape), [tuple(p.shape) for p in f.grids.factors]
    ((5,), (5, 3), [(4, 4), (4, 4), (4, 4), (4, 4)])
    """

    def __init__(self, rank: int = 8, resolution_init: Sequence[int] = (16, 16, 16, 16),
                 resolution_final: Sequence[int] = (128, 128, 128, 24), n_growth: int = 10,
                 growth_until: float = 0.2, init_scale: float = 0.2,
                 decoder: Literal["linear", "mlp"] = "linear", decoder_hidden: int = 64,
                 decoder_lr_scale: float = 0.1, density_shift: float = 0.0,
                 density_activation: DensityActivation = "trunc_exp", bound: float = 1.0,
                 seed: int = 0):
        init = [(0.0, init_scale)] * 3 + [(1.0, 1e-2)]
        super().__init__([(0,), (1,), (2,), (3,)], init, rank, rank, resolution_init,
                         resolution_final, n_growth, growth_until, decoder, decoder_hidden,
                         decoder_lr_scale, density_shift, density_activation, bound, seed)

    def components(self, samples: list[Tensor]) -> tuple[Tensor, Tensor]:
        """``f = v_x * v_y * v_z * v_t`` (each ``[2R, N]``) -> (density, appearance) halves."""
        f = samples[0] * samples[1] * samples[2] * samples[3]
        return f[: self.rank], f[self.rank :]
