"""Common base of the factorised backbones (TensoRF-CP 4D, HexPlane), as the authors
build them.

A factorised field holds :class:`~baselines.grids.FactorGrids` with ``F·R`` channels:
``F = 4`` output features (raw density and three raw colours) times rank ``R``. A
subclass says which factors exist and how their samples combine (:meth:`combine`, a
product per rank component); the rank is then summed directly,

.. math:: \\mathbf{o}_f(\\mathbf{c}) = \\sum_{r=1}^{R} g_{f R + r}(\\mathbf{c}),\\quad
          \\sigma = \\mathrm{trunc\\_exp}(o_0),\\quad
          \\mathbf{rgb} = \\mathrm{sigmoid}(o_{1..3}),

with no decoder network (the authors' ``res.view(N, F, R).sum(-1)``). Coordinates are
the world positions normalised to the clipping cylinder's bounding box
(:meth:`set_scene_box`, called by the run with its renderer's cylinder) and ``2t − 1``.
Every factor starts as ``N(0, (init_gain / R)²)``.

The rank sum has two implementations behind ``implementation``
(:mod:`eventrecon.kernels`): the PyTorch reference (:meth:`FactorisedField.rank_sum`
over ``grid_sample``) and a subclass's compiled CPU kernel (:meth:`kernel`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from baselines.grids import FactorGrids, box_normalize
from baselines.heads import activate, activate_density
from baselines.schedules import GridGrowth, GrowthPlan
from eventrecon.common.errors import InputError
from eventrecon.fields.base import Field
from eventrecon.kernels import resolve, use_kernel

#: Output features per rank component: raw density and three raw colours.
FEATURES = 4


class FactorisedField(Field):
    """Field ``(xyz, t) -> (sigma, rgb)`` from rank-summed products of dense factor grids.

    Args:
        axes: input axes spanned by each factor (see :class:`FactorGrids`).
        align_corners: sampling convention of each factor.
        rank: components ``R`` per output feature.
        plan: the growth of the per-axis resolution ``(x, y, z, t)``.
        init_gain: factors start as ``N(0, (init_gain / R)²)``.
        seed: initialisation seed.
        implementation: ``"auto"``, ``"torch"`` or ``"numba"`` (:mod:`eventrecon.kernels`).
    """

    def __init__(self, axes: Sequence[Sequence[int]], align_corners: Sequence[bool],
                 rank: int, plan: GrowthPlan, init_gain: float, seed: int,
                 implementation: str = "auto"):
        super().__init__()
        self.implementation = resolve(implementation)
        if rank < 1:
            raise InputError("conf/model", "rank", "an integer >= 1", rank)
        for name, res in (("resolution_init", plan.start), ("resolution_final", plan.end)):
            if len(res) != 4 or min(res) < 2:
                raise InputError("conf/model", name, "4 resolutions (x, y, z, t), each >= 2",
                                 list(res))
        self.rank = int(rank)
        self.plan = plan
        gen = torch.Generator().manual_seed(seed)
        self.grids = FactorGrids(axes, FEATURES * self.rank, self.shapes(plan.initial),
                                 init_gain / self.rank, align_corners, "zeros", gen)
        self.register_buffer("box_lo", torch.tensor([-1.0, -1.0, -1.0]), persistent=False)
        self.register_buffer("box_hi", torch.tensor([1.0, 1.0, 1.0]), persistent=False)

    def shapes(self, resolution: Sequence[int]) -> list[tuple[int, ...]]:
        """Each factor's grid shape at the per-axis ``resolution``."""
        raise NotImplementedError

    @property
    def resolution(self) -> tuple[int, ...]:
        """The current per-axis resolution ``(x, y, z, t)``, read off the factors' shapes
        (so a grown checkpoint loaded into a fresh field reports its own)."""
        raise NotImplementedError

    def combine(self, samples: list[Tensor]) -> Tensor:
        """Factor samples → rank components, channel by channel: ``[N, F·R]`` each
        (:func:`~baselines.grids.sample_points`)."""
        raise NotImplementedError

    def set_scene_box(self, lo: Sequence[float], hi: Sequence[float]) -> None:
        """The world box mapped to ``[-1, 1]^3`` (the clipping cylinder's bounding box)."""
        self.box_lo.copy_(torch.as_tensor(lo, dtype=self.box_lo.dtype))
        self.box_hi.copy_(torch.as_tensor(hi, dtype=self.box_hi.dtype))

    def upsample(self, resolution: Sequence[int]) -> None:
        """Grow every factor to ``resolution`` (new Parameters; rebuild the optimiser)."""
        self.grids.upsample(self.shapes(resolution))

    def forward(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        """``xyz [N, 3], t [N, 1] -> (sigma [N], rgb [N, 3])``."""
        out = self.rank_sum(box_normalize(xyz, t, self.box_lo, self.box_hi))
        return activate(out[:, 0], out[:, 1:])

    def density_only(self, xyz: Tensor, t: Tensor) -> Tensor:
        """``sigma [N]`` from the density's ``R`` channels alone (the first of the
        ``F·R``; what the occupancy grid asks): :meth:`forward`'s σ, a quarter of the
        factors' channels read."""
        out = self.rank_sum(box_normalize(xyz, t, self.box_lo, self.box_hi), features=1)
        return activate_density(out[:, 0])

    def rank_sum(self, coords: Tensor, features: int = FEATURES) -> Tensor:
        """``o [N, features]``: the first ``features`` outputs' rank components at
        ``coords [N, 4]`` summed over the rank (channel ``f·R + r`` is output ``f``'s
        component ``r``). The reference samples each factor with ``grid_sample``
        (:func:`~baselines.grids.sample_points`), combines the samples (:meth:`combine`)
        and sums; :meth:`kernel` computes the same where ``implementation`` chooses it."""
        factors = self.grids.leading(self.channels(features))
        if use_kernel(self.implementation, self.kernel_unsupported(factors, coords)):
            return self.kernel(factors, coords)
        out = self.combine(self.grids(coords, self.channels(features)))  # [N, features·R]
        return out.reshape(-1, features, self.rank).sum(-1)

    def kernel_unsupported(self, factors: list[Tensor], coords: Tensor) -> str | None:
        """What the compiled rank sum needs and this call lacks (``None``: it applies)."""
        return "a compiled kernel for this backbone"

    def kernel(self, factors: list[Tensor], coords: Tensor) -> Tensor:
        """The compiled rank sum of ``factors`` at ``coords``: :meth:`rank_sum`'s values."""
        raise NotImplementedError

    def channels(self, features: int) -> int | None:
        """The leading channels of each factor that the first ``features`` outputs read;
        ``None`` for all (:meth:`~baselines.grids.FactorGrids.leading`)."""
        return None if features == FEATURES else features * self.rank

    def callbacks(self) -> list[Any]:
        """Grid growth (upsampling + optimiser rebuild) when the plan has stages."""
        return [GridGrowth(self, self.plan)] if self.plan.n_stages > 1 else []
