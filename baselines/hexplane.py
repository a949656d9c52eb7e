"""HexPlane as the authors built it: three spatial planes, three space-time planes and
three spatial lines.

With ``c`` the coordinates normalised to the clipping cylinder's box
(:mod:`baselines.factorised`), the rank components are

.. math:: g = P_{xy}(c_x, c_y)\\, P_{zt}(c_z, c_t)\\, v_x(c_x)
          + P_{xz}(c_x, c_z)\\, P_{yt}(c_y, c_t)\\, v_y(c_y)
          + P_{yz}(c_y, c_z)\\, P_{xt}(c_x, c_t)\\, v_z(c_z),

each factor with ``F·R`` channels, summed over the rank into the raw density and the
three raw colours (the authors' ``XY·ZT·x + XZ·YT·y + YZ·XT·z``; no decoder). Planes are
sampled with ``align_corners=True``, lines with ``False`` (their ``sample_mat`` /
``sample_vec``), zero padding. Sizes: the spatial planes and lines have ``N`` vertices
per axis; a space-time plane is allocated ``[N, N_t]`` but sampled with the space
coordinate as ``grid_sample``'s x, which indexes the last (``N_t``) dimension, and time
as y: in the authors' model a space-time plane resolves space with ``N_t = 24`` vertices
and time with ``N = 500``. That layout is kept (``spacetime_layout="authors"``);
``"swapped"`` gives space ``N`` and time ``N_t`` vertices. No growth, no total variation
(the authors' configuration); the supplementary's sizes are ``N = 500``, ``N_t = 24``,
rank 8.
"""

from __future__ import annotations

from collections.abc import Sequence

from torch import Tensor

from baselines.factorised import FactorisedField
from baselines.schedules import GrowthPlan
from eventrecon.common.errors import InputError
from eventrecon.kernels import factor_grids

#: (spatial plane axes, space-time plane axes as the authors sample them, line axis):
#: axes 0..3 = (x, y, z, t); a plane's first axis indexes its first grid dimension.
TERMS: tuple[tuple[tuple[int, int], tuple[int, int], int], ...] = (
    ((1, 0), (3, 2), 0), ((2, 0), (3, 1), 1), ((2, 1), (3, 0), 2))


class HexPlaneField(FactorisedField):
    """HexPlane field; see the module docstring for the maths.

    Args:
        rank: components ``R`` per output feature.
        resolution: vertices ``(N, N, N, N_t)``; the spatial axes must agree.
        spacetime_layout: ``"authors"`` (space ``N_t``, time ``N`` vertices in the
            space-time planes) or ``"swapped"``.
        init_gain: factors start as ``N(0, (init_gain / R)²)``.
        seed: initialisation seed.
        implementation: the rank sum's (:mod:`eventrecon.kernels`).

    >>> import torch
    >>> f = HexPlaneField(rank=2, resolution=(8, 8, 8, 6))
    >>> sigma, rgb = f(torch.zeros(5, 3), torch.full((5, 1), 0.5))
    >>> tuple(sigma.shape), tuple(rgb.shape), [tuple(p.shape[1:]) for p in f.grids.factors][3:6]
    ((5,), (5, 3), [(8, 6), (8, 6), (8, 6)])
    """

    def __init__(self, rank: int = 8, resolution: Sequence[int] = (500, 500, 500, 24),
                 spacetime_layout: str = "authors", init_gain: float = 1.0, seed: int = 0,
                 implementation: str = "auto"):
        if spacetime_layout not in ("authors", "swapped"):
            raise InputError("conf/model", "spacetime_layout", "authors or swapped",
                             spacetime_layout)
        self.spacetime_layout = spacetime_layout
        axes = ([s for s, _, _ in TERMS] + [st for _, st, _ in TERMS]
                + [(line,) for _, _, line in TERMS])
        plan = GrowthPlan(tuple(resolution), tuple(resolution), 1, 0)
        super().__init__(axes, [True] * 6 + [False] * 3, rank, plan, init_gain, seed,
                         implementation)

    def shapes(self, resolution: Sequence[int]) -> list[tuple[int, ...]]:
        """Three ``[N, N]`` planes, three space-time planes, three ``[N]`` lines."""
        n, n_t = int(resolution[0]), int(resolution[3])
        if not resolution[0] == resolution[1] == resolution[2]:
            raise InputError("conf/model", "resolution", "the same N along x, y and z",
                             list(resolution))
        spacetime = (n, n_t) if self.spacetime_layout == "authors" else (n_t, n)
        return [(n, n)] * 3 + [spacetime] * 3 + [(n,)] * 3

    @property
    def resolution(self) -> tuple[int, ...]:
        n = self.grids.shapes[0][0]
        st = self.grids.shapes[3]
        return (n, n, n, st[1] if self.spacetime_layout == "authors" else st[0])

    def combine(self, samples: list[Tensor]) -> Tensor:
        """``Σ_k P_space,k · P_spacetime,k · v_k`` per channel."""
        return sum(samples[k] * samples[k + 3] * samples[k + 6] for k in range(3))

    def kernel_unsupported(self, factors: list[Tensor], coords: Tensor) -> str | None:
        return factor_grids.hex_unsupported(factors, self.grids.axes, coords,
                                            self.grids.align_corners)

    def kernel(self, factors: list[Tensor], coords: Tensor) -> Tensor:
        """One compiled pass over the nine factors (:func:`~eventrecon.kernels.factor_grids.
        hex_rank_sum`)."""
        return factor_grids.hex_rank_sum(factors, self.grids.axes, coords,
                                         self.grids.align_corners, self.grids.padding,
                                         self.rank)
