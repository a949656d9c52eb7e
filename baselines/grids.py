"""Dimension-agnostic dense-grid helpers shared by the factorised backbones.

A *factor grid* is a tensor ``[C, R_0, ..., R_{d-1}]`` of ``C`` feature channels over
``d`` input axes (a line ``d = 1``, a plane ``d = 2``); ``coords[:, k]`` in ``[-1, 1]``
indexes grid axis ``k``. Two sampling conventions of ``grid_sample`` are used, as in the
authors' code: ``align_corners=True`` puts coordinate ``−1`` on vertex ``0`` and ``+1``
on vertex ``R − 1``; ``align_corners=False`` puts them on the outer edges of the first
and last cells (vertex ``i`` sits at ``(2i + 1)/R − 1``). Outside the sampled range the
grid is extended by its border values (``padding="border"``) or by zeros
(``padding="zeros"``, ``grid_sample``'s default, which the authors' code uses).
On a CPU a :class:`FactorGrids` factor keeps that shape but stores its channels
innermost (:func:`channels_last`), the layout the compiled rank sums of
:mod:`eventrecon.kernels.factor_grids` read as rows.

Scene normalisation (:func:`box_normalize`): world ``xyz`` is mapped from a box (the
clipping cylinder's bounding box, set by the run) to ``[-1, 1]^3`` and the segment time
``t in [0, 1]`` to ``2t - 1``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

_MODES = {1: "linear", 2: "bilinear", 3: "trilinear"}


def box_normalize(xyz: Tensor, t: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """Map world positions in the box ``[lo, hi]`` and segment time to ``[-1, 1]^4``.

    ``c_k = 2 (x_k − lo_k) / (hi_k − lo_k) − 1`` for ``k = x, y, z`` and ``c_t = 2t − 1``.

    Args:
        xyz: ``[N, 3]`` world positions.
        t: ``[N, 1]`` (or ``[N]``) normalised time in ``[0, 1]``.
        lo, hi: ``[3]`` box corners.

    Returns:
        ``[N, 4]`` normalised coordinates.

    >>> box_normalize(torch.tensor([[0.5, -0.75, 0.0]]), torch.tensor([[0.25]]),
    ...               torch.tensor([-0.5, -0.75, -0.5]), torch.tensor([0.5, 0.25, 0.5])).tolist()
    [[1.0, -1.0, 0.0, -0.5]]
    """
    lo, hi = lo.to(xyz), hi.to(xyz)
    c = 2.0 * (xyz - lo) / (hi - lo) - 1.0
    return torch.cat([c, 2.0 * t.reshape(-1, 1).to(xyz.dtype) - 1.0], dim=-1)


def vertex_coords(coords: Tensor, sizes: Sequence[int], align_corners: bool,
                  padding: str) -> Tensor:
    """Normalised coordinates ``[N, d]`` in ``[-1, 1]`` → vertex units ``[N, d]``, by
    ``grid_sample``'s formulas: ``(c + 1)/2 · (R − 1)`` (``align_corners``) or
    ``((c + 1) R − 1)/2``; ``padding="border"`` clamps to ``[0, R − 1]``.

    >>> vertex_coords(torch.tensor([[-1.0], [1.0]]), (5,), True, "zeros").flatten().tolist()
    [0.0, 4.0]
    >>> vertex_coords(torch.tensor([[-1.0], [1.0]]), (5,), False, "zeros").flatten().tolist()
    [-0.5, 4.5]
    """
    res = torch.tensor(list(sizes), dtype=coords.dtype, device=coords.device)
    p = (coords + 1) / 2 * (res - 1) if align_corners else ((coords + 1) * res - 1) / 2
    if padding == "border":
        p = torch.minimum(p.clamp(min=0), res - 1)
    return p


def sample_points(grid: Tensor, coords: Tensor, align_corners: bool = True,
                  padding: str = "border", axes: Sequence[int] | None = None) -> Tensor:
    """:func:`sample_grid`, channel-last: ``[N, C]``. With ``axes``, ``coords [N, D]`` and
    grid axis ``k`` reads column ``axes[k]``."""
    if axes is not None:
        coords = coords[:, list(axes)]
    d = grid.dim() - 1
    if d == 1:  # a line as an [R, 1] image; the dummy width coordinate samples column 0
        img = grid.unsqueeze(-1).unsqueeze(0)
        g = torch.stack([torch.zeros_like(coords[:, 0]), coords[:, 0]], dim=-1)
    else:  # grid_sample wants (x -> last axis, y -> previous axis, ...): reversed order
        img = grid.unsqueeze(0)
        g = coords.flip(-1)
    g = g.to(img.dtype).reshape(1, -1, *([1] * (max(d, 2) - 1)), g.shape[-1])
    out = F.grid_sample(img, g, mode="bilinear", padding_mode=padding,
                        align_corners=align_corners)                 # [1, C, N, 1…]
    return out.reshape(grid.shape[0], -1).t()


def sample_grid(grid: Tensor, coords: Tensor, align_corners: bool = True,
                padding: str = "border") -> Tensor:
    """Multilinear interpolation of a dense ``d``-dimensional grid (``d`` = 1, 2 or 3).

    ``f(c) = sum_corners prod_k w_k * grid[:, i_0 + b_0, ..., i_{d-1} + b_{d-1}]`` with
    ``p_k = (c_k + 1) / 2 * (R_k - 1)`` (``align_corners=True``) or
    ``p_k = ((c_k + 1) R_k - 1) / 2`` (``False``), ``i_k = floor(p_k)``, ``w_k = p_k - i_k``
    for ``b_k = 1`` and ``1 - (p_k - i_k)`` for ``b_k = 0``; vertices outside the grid take
    the border value or zero (``padding``).

    Args:
        grid: ``[C, R_0, ..., R_{d-1}]`` features.
        coords: ``[N, d]`` coordinates; ``coords[:, k]`` indexes axis ``k``.
        align_corners, padding: the convention (module docstring).

    Returns:
        ``[C, N]`` interpolated features, channel-first (a transposed view of
        :func:`sample_points`).

    >>> line = torch.tensor([[0.0, 1.0, 4.0]])      # C = 1, R = 3
    >>> sample_grid(line, torch.tensor([[-1.0], [0.5], [2.0]])).flatten().tolist()
    [0.0, 2.5, 4.0]
    >>> sample_grid(line, torch.tensor([[0.0], [1.0]]), False, "zeros").flatten().tolist()
    [1.0, 2.0]
    """
    return sample_points(grid, coords, align_corners, padding).t()


def sample_grid_reference(grid: Tensor, coords: Tensor, align_corners: bool = True,
                          padding: str = "border") -> Tensor:
    """Slow, explicit version of :func:`sample_grid`: a Python loop over the ``2^d`` corners
    with integer gathers. Same shapes (``[C, N]``) and conventions; for tests. The vertex
    units are :func:`vertex_coords`' (the tests check them against ``grid_sample``, which
    computes its own)."""
    d = grid.dim() - 1
    sizes = tuple(grid.shape[1:])
    pos = vertex_coords(coords, sizes, align_corners, padding)
    i0 = pos.floor().long()
    frac = pos - i0.to(pos.dtype)
    flat = grid.reshape(grid.shape[0], -1)
    strides = [math.prod(grid.shape[2 + k:]) for k in range(d)]
    out = torch.zeros(grid.shape[0], coords.shape[0], dtype=grid.dtype, device=grid.device)
    for corner in itertools.product((0, 1), repeat=d):
        w = torch.ones_like(frac[:, 0])
        lin = torch.zeros_like(i0[:, 0])
        valid = torch.ones_like(frac[:, 0], dtype=torch.bool)
        for k, b in enumerate(corner):
            w = w * (frac[:, k] if b else 1 - frac[:, k])
            idx = i0[:, k] + b
            valid &= (idx >= 0) & (idx <= sizes[k] - 1)
            lin = lin + idx.clamp(0, sizes[k] - 1) * strides[k]
        out = out + (w * valid)[None, :] * flat[:, lin]
    return out


def upsample_grid(grid: Tensor, size: Sequence[int], align_corners: bool = True) -> Tensor:
    """Resample a grid to a new vertex count by multilinear interpolation in the grid's own
    convention: each new vertex takes the old interpolant's value at its position (with
    ``align_corners=False`` the outermost new vertices, beyond the old outer vertices,
    take the border values, as ``F.interpolate`` does and as the authors' growth does).

    Args:
        grid: ``[C, R_0, ..., R_{d-1}]``.
        size: new ``(R'_0, ..., R'_{d-1})``.
        align_corners: the grid's sampling convention.

    Returns:
        ``[C, R'_0, ..., R'_{d-1}]``. With ``align_corners=True`` and ``R'_k - 1`` a
        multiple of ``R_k - 1`` the new interpolant equals the old one everywhere (up to
        rounding); otherwise the change is bounded by
        ``sum_k (h'_k / 4 h_k) max |second difference_k|``.
    """
    d = grid.dim() - 1
    out = F.interpolate(grid.unsqueeze(0), size=tuple(int(s) for s in size), mode=_MODES[d],
                        align_corners=align_corners)
    return out[0]


def geometric_resolutions(start: Sequence[int], end: Sequence[int], n_stages: int
                          ) -> list[tuple[int, ...]]:
    """Per-axis resolutions of ``n_stages`` growth stages, geometric from ``start`` to
    ``end``, truncated to integers as the authors' code does
    (``int(geomspace(start, end, n_stages)[k])``).

    >>> geometric_resolutions([16, 16], [500, 24], 10)[:3]
    [(16, 16), (23, 16), (34, 17)]
    >>> geometric_resolutions([16, 16], [500, 24], 10)[-1]
    (500, 24)
    """
    if n_stages <= 1:
        return [tuple(int(e) for e in end)]
    out = []
    for k in range(n_stages):
        f = k / (n_stages - 1)
        res = []
        for s, e in zip(start, end):
            v = s * (e / s) ** f
            res.append(int(e) if k == n_stages - 1 else int(v + 1e-9))
        out.append(tuple(res))
    return out


def channels_last(grid: Tensor) -> Tensor:
    """``grid [C, R_0, …]`` with the same shape and values, its channels innermost in
    memory (strides ``(1, …, C)``): the rows :mod:`eventrecon.kernels.factor_grids` reads
    without a copy, and the layout of its gradient, which autograd keeps as it comes.

    >>> channels_last(torch.zeros(4, 5, 6)).stride()
    (1, 24, 4)
    """
    return grid.movedim(0, -1).contiguous().movedim(-1, 0)


def device_layout(grid: Tensor) -> Tensor:
    """A factor's layout on its device: :func:`channels_last` on a CPU, contiguous
    elsewhere (where ``grid_sample`` reads it and fused optimisers step it)."""
    return channels_last(grid) if grid.device.type == "cpu" else grid.contiguous()


class FactorGrids(nn.Module):
    """Dense factor grids over subsets of the 4 input axes ``(x, y, z, t)``.

    Factor ``j`` spans the input axes ``axes[j]`` (in grid-axis order: ``coords[:, axes[j][k]]``
    indexes its grid axis ``k``) and has shape ``[C, *shapes[j]]``.

    Args:
        axes: input axes per factor.
        channels: feature channels ``C`` of every factor.
        shapes: vertices per grid axis of each factor.
        std: initial values ``N(0, std²)`` (the authors: ``1 / rank``).
        align_corners, padding: the sampling convention per factor
            (:func:`sample_grid`).
        generator: random generator for the initialisation.
    """

    def __init__(self, axes: Sequence[Sequence[int]], channels: int,
                 shapes: Sequence[Sequence[int]], std: float,
                 align_corners: Sequence[bool], padding: str = "zeros",
                 generator: torch.Generator | None = None):
        super().__init__()
        self.axes = [tuple(a) for a in axes]
        self.align_corners = [bool(a) for a in align_corners]
        self.padding = padding
        self.factors = nn.ParameterList()
        for shape in shapes:
            val = std * torch.randn((channels, *shape), generator=generator)
            self.factors.append(nn.Parameter(device_layout(val)))

    @property
    def shapes(self) -> list[tuple[int, ...]]:
        """Vertices per grid axis of each factor."""
        return [tuple(f.shape[1:]) for f in self.factors]

    def leading(self, channels: int | None) -> list[Tensor]:
        """The factors, or the first ``channels`` of each; ``None``: the factors themselves,
        unsliced (a slice's backward would allocate and copy a factor-sized gradient)."""
        return list(self.factors) if channels is None else [f[:channels] for f in self.factors]

    def forward(self, coords: Tensor, channels: int | None = None) -> list[Tensor]:
        """Sample every factor (:meth:`leading`): ``coords [N, 4]`` -> list of ``[N, C]``
        (:func:`sample_points`)."""
        return [sample_points(f, coords, ac, self.padding, ax)
                for f, ax, ac in zip(self.leading(channels), self.axes, self.align_corners)]

    def upsample(self, shapes: Sequence[Sequence[int]]) -> None:
        """Replace every factor by a new Parameter resampled to ``shapes[j]``."""
        with torch.no_grad():
            for j, shape in enumerate(shapes):
                if tuple(shape) != self.shapes[j]:
                    new = upsample_grid(self.factors[j].detach(), shape, self.align_corners[j])
                    self.factors[j] = nn.Parameter(device_layout(new))

    def _apply(self, fn: Any, recurse: bool = True) -> FactorGrids:  # type: ignore[override]
        """After a move or cast (``.to``, ``.cuda``, ``.double``) every factor takes its
        device's layout (:func:`device_layout`)."""
        super()._apply(fn, recurse)
        for f in self.factors:
            f.data = device_layout(f.data)
            if f.grad is not None:
                f.grad = device_layout(f.grad)
        return self

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):  # type: ignore[override]
        # A checkpoint written after growth holds larger factors: resize before loading.
        for j in range(len(self.factors)):
            saved = state_dict.get(f"{prefix}factors.{j}")
            if saved is not None and tuple(saved.shape) != tuple(self.factors[j].shape):
                device = self.factors[j].device
                blank = torch.empty(saved.shape, dtype=self.factors[j].dtype, device=device)
                self.factors[j] = nn.Parameter(device_layout(blank))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
