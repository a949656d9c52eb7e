"""Dimension-agnostic dense-grid helpers shared by the factorised backbones.

Conventions (K-Planes style): a *factor grid* is a tensor ``[C, R_0, ..., R_{d-1}]`` of
``C`` feature channels over ``d`` of the four input axes ``(x, y, z, t)``; a line is
``d = 1``, a plane ``d = 2``. Grids are sampled at coordinates in ``[-1, 1]`` with
``align_corners=True``: coordinate ``-1`` is vertex ``0``, ``+1`` is vertex ``R - 1``,
and coordinates outside ``[-1, 1]`` are clamped to the border (the field is extended
by its boundary values).

Scene normalisation (:func:`normalize_xyzt`): world ``xyz`` lies in the unit sphere and
the clipping cylinder inside ``[-1, 1]^3``, so ``xyz`` is divided by ``bound = 1``;
the segment time ``t in [0, 1]`` maps to ``2t - 1``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

_MODES = {1: "linear", 2: "bilinear", 3: "trilinear"}


def normalize_xyzt(xyz: Tensor, t: Tensor, bound: float = 1.0) -> Tensor:
    """Map world positions and segment time to ``[-1, 1]^4``.

    ``c = (x / bound, y / bound, z / bound, 2 t - 1)``.

    Args:
        xyz: ``[N, 3]`` world positions.
        t: ``[N, 1]`` (or ``[N]``) normalised time in ``[0, 1]``.
        bound: half-size of the box ``[-bound, bound]^3`` mapped to ``[-1, 1]^3``.

    Returns:
        ``[N, 4]`` normalised coordinates.

    >>> normalize_xyzt(torch.tensor([[1.0, -0.5, 0.0]]), torch.tensor([[0.25]])).tolist()
    [[1.0, -0.5, 0.0, -0.5]]
    """
    return torch.cat([xyz / bound, 2.0 * t.reshape(-1, 1).to(xyz.dtype) - 1.0], dim=-1)


def sample_grid(grid: Tensor, coords: Tensor) -> Tensor:
    """Multilinear interpolation of a dense ``d``-dimensional grid (``d`` = 1, 2 or 3).

    ``f(c) = sum_corners prod_k w_k * grid[:, i_0 + b_0, ..., i_{d-1} + b_{d-1}]`` with
    ``p_k = (c_k + 1) / 2 * (R_k - 1)`` (clamped to the grid), ``i_k = floor(p_k)``,
    ``w_k = p_k - i_k`` for ``b_k = 1`` and ``1 - (p_k - i_k)`` for ``b_k = 0``; computed
    by ``torch.nn.functional.grid_sample`` (a line is sampled as an ``[R, 1]`` image).

    Args:
        grid: ``[C, R_0, ..., R_{d-1}]`` features.
        coords: ``[N, d]`` coordinates in ``[-1, 1]``; ``coords[:, k]`` indexes axis ``k``.

    Returns:
        ``[C, N]`` interpolated features, channel-first (the layout grid_sample produces;
        products of factors then run on contiguous memory).

    >>> line = torch.tensor([[0.0, 1.0, 4.0]])      # C = 1, R = 3
    >>> sample_grid(line, torch.tensor([[-1.0], [0.5], [2.0]])).flatten().tolist()
    [0.0, 2.5, 4.0]
    """
    d = grid.dim() - 1
    n = coords.shape[0]
    if d == 1:  # a line as an [R, 1] image; the dummy width coordinate samples column 0
        img = grid.unsqueeze(-1).unsqueeze(0)
        g = torch.stack([torch.zeros_like(coords[:, 0]), coords[:, 0]], dim=-1)
        g = g.view(1, n, 1, 2)
    else:  # grid_sample wants (x -> last axis, y -> previous axis, ...): reversed order
        img = grid.unsqueeze(0)
        g = coords.flip(-1).view(1, n, *([1] * (d - 1)), d)
    g = g.to(img.dtype)
    out = F.grid_sample(img, g, mode="bilinear", padding_mode="border", align_corners=True)
    return out.reshape(grid.shape[0], n)


def sample_grid_reference(grid: Tensor, coords: Tensor) -> Tensor:
    """Slow, explicit version of :func:`sample_grid`: a Python loop over the ``2^d`` corners
    with integer gathers. Same shapes (``[C, N]``) and convention; for tests and benchmarks."""
    d = grid.dim() - 1
    res = torch.tensor(grid.shape[1:], device=coords.device)
    pos = (coords.clamp(-1, 1) + 1) / 2 * (res - 1).to(coords.dtype)
    i0 = pos.floor().long().clamp(min=torch.zeros_like(res), max=(res - 2).clamp(min=0))
    frac = pos - i0.to(pos.dtype)
    flat = grid.reshape(grid.shape[0], -1)
    strides = [math.prod(grid.shape[2 + k :]) for k in range(d)]
    out = torch.zeros(grid.shape[0], coords.shape[0], dtype=grid.dtype, device=grid.device)
    for corner in itertools.product((0, 1), repeat=d):
        w = torch.ones_like(frac[:, 0])
        lin = torch.zeros_like(i0[:, 0])
        for k, b in enumerate(corner):
            w = w * (frac[:, k] if b else 1 - frac[:, k])
            lin = lin + (i0[:, k] + b).clamp(max=int(res[k]) - 1) * strides[k]
        out = out + w[None, :] * flat[:, lin]
    return out


def upsample_grid(grid: Tensor, size: Sequence[int]) -> Tensor:
    """Resample a grid to a new vertex count by multilinear interpolation
    (``align_corners=True``): each new vertex takes the old interpolant's value there.

    Args:
        grid: ``[C, R_0, ..., R_{d-1}]``.
        size: new ``(R'_0, ..., R'_{d-1})``.

    Returns:
        ``[C, R'_0, ..., R'_{d-1}]``. When ``R'_k - 1`` is a multiple of ``R_k - 1`` the
        new interpolant equals the old one everywhere (up to float rounding); otherwise
        the error is bounded by ``sum_k (h'_k / 4 h_k) max |second difference_k|``.
    """
    d = grid.dim() - 1
    out = F.interpolate(grid.unsqueeze(0), size=tuple(int(s) for s in size), mode=_MODES[d],
                        align_corners=True)
    return out[0]


def total_variation(grid: Tensor, dims: Sequence[int] | None = None) -> Tensor:
    """Mean squared forward difference, summed over grid axes.

    ``TV(g) = sum_k mean((g[..., i_k + 1, ...] - g[..., i_k, ...])^2)`` over the axes
    ``k`` in ``dims`` (tensor dimensions; default every axis after the channel axis 0);
    a scalar.

    >>> float(total_variation(torch.tensor([[0.0, 1.0, 3.0]])))
    2.5
    >>> g = torch.tensor([[[0.0, 2.0], [1.0, 3.0]]])   # [C=1, 2, 2]
    >>> float(total_variation(g, dims=(1,))), float(total_variation(g, dims=(2,)))
    (1.0, 4.0)
    """
    dims = range(1, grid.dim()) if dims is None else dims
    return sum(grid.diff(dim=k).square().mean() for k in dims)


def geometric_resolutions(start: Sequence[int], end: Sequence[int], n_steps: int
                          ) -> list[tuple[int, ...]]:
    """Per-axis resolutions growing geometrically from ``start`` to ``end``.

    ``R_k = round(start * (end / start)^(k / n_steps))`` for ``k = 0..n_steps``.

    >>> geometric_resolutions([16, 16], [64, 24], 2)
    [(16, 16), (32, 20), (64, 24)]
    """
    out = []
    for k in range(n_steps + 1):
        f = k / n_steps if n_steps else 1.0
        out.append(tuple(int(round(s * (e / s) ** f)) for s, e in zip(start, end)))
    return out


class FactorGrids(nn.Module):
    """A set of dense factor grids over subsets of the 4 input axes.

    ``axes`` lists, per factor, the input axes it spans, e.g. ``[(0,), (1,), (2,), (3,)]``
    for CP lines or ``itertools.combinations(range(4), 2)`` for the six HexPlane planes.
    Factor ``j`` is ``[C, R[a] for a in axes[j]]`` with the per-axis resolution ``R``.

    Args:
        axes: axis tuples, one per factor.
        channels: feature channels ``C`` per factor.
        resolution: vertices per input axis (length 4).
        init: per factor, ``(mean, std)`` of the Gaussian initialisation.
        generator: random generator for the initialisation.
    """

    def __init__(self, axes: Sequence[Sequence[int]], channels: int, resolution: Sequence[int],
                 init: Sequence[tuple[float, float]], generator: torch.Generator | None = None):
        super().__init__()
        self.axes = [tuple(a) for a in axes]
        self.resolution = tuple(int(r) for r in resolution)
        self.factors = nn.ParameterList()
        for ax, (mean, std) in zip(self.axes, init, strict=True):
            shape = (channels, *(self.resolution[a] for a in ax))
            val = mean + std * torch.randn(shape, generator=generator)
            self.factors.append(nn.Parameter(val))

    def forward(self, coords: Tensor) -> list[Tensor]:
        """Sample every factor: ``coords [N, 4]`` in ``[-1, 1]`` -> list of ``[C, N]``."""
        return [sample_grid(f, coords[:, list(ax)]) for f, ax in zip(self.factors, self.axes)]

    def upsample(self, resolution: Sequence[int]) -> None:
        """Replace every factor by a new Parameter resampled to ``resolution``."""
        self.resolution = tuple(int(r) for r in resolution)
        with torch.no_grad():
            for j, ax in enumerate(self.axes):
                new = upsample_grid(self.factors[j].detach(), [self.resolution[a] for a in ax])
                self.factors[j] = nn.Parameter(new.contiguous())

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):  # type: ignore[override]
        # A checkpoint written after growth holds larger factors: resize before loading.
        res = list(self.resolution)
        for j, ax in enumerate(self.axes):
            saved = state_dict.get(f"{prefix}factors.{j}")
            if saved is not None and tuple(saved.shape) != tuple(self.factors[j].shape):
                device = self.factors[j].device
                self.factors[j] = nn.Parameter(torch.empty_like(saved, device=device))
                for a, r in zip(ax, saved.shape[1:]):
                    res[a] = int(r)
        self.resolution = tuple(res)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
