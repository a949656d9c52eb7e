"""Multilinear interpolation of dense grids on the CPU, channel-last, with its gradient.

A grid ``G [C, R_0, …, R_{d-1}]`` (``d`` = 1, 2 or 3: the factorised backbones' lines
and planes) is read at ``N`` points given in vertex units ``p [N, d]``
(:func:`vertex_coords`: ``p_k = i`` on vertex ``i``):

.. math::
    f_n = \\sum_{b \\in \\{0,1\\}^d} \\Big(\\prod_k w_k(b_k)\\Big)\\,
          G[:, i_0 + b_0, \\dots, i_{d-1} + b_{d-1}],\\quad
    i_k = \\lfloor p_k \\rfloor,\\ w_k(1) = p_k - i_k,\\ w_k(0) = 1 - w_k(1),

a corner outside the grid adding nothing (``grid_sample``'s zero padding; border padding
clamps ``p`` first). Its gradient with respect to the grid is the transposed scatter,

.. math::
    \\frac{\\partial L}{\\partial G[:, v]} = \\sum_n \\sum_{b:\\ i(n) + b = v}
    \\Big(\\prod_k w_k(b_k)\\Big) \\frac{\\partial L}{\\partial f_n}.

Why not ``grid_sample``: its CPU kernels keep the channels outermost, so each corner
costs ``C`` strided reads, and its backward accumulates one batch entry per thread into
a full-size gradient buffer. Here the grid is read channel-last (``[R_0, …, C]``, one
contiguous row of ``C`` values per vertex; the factors are stored so on a CPU,
:func:`~baselines.grids.device_layout`) at its ``2^d`` corners by compiled loops
(numba). At 13 000 points, forward and backward, a 128² plane of 32 channels takes
2.3 ms against 7.2 ms on one thread, a line 3.5–4.9× less (docs/results/history.md,
"Session 50"). With two or more torch threads the points are split into ranges run on
numba's threads (:func:`eventrecon.sim.jit.parts`; HexPlane's training step 1.16×
faster on 2 cores, "Session 57"), the backward's ranges each scattering into their own
copy of the grid's gradient while the points' corners outnumber its vertices; the copies
are summed, so the gradient then agrees with one thread's to rounding.

The values are the corner gather's: ``grid_sample``'s up to the rounding of the weights.
A point with a non-finite coordinate reads NaN, as with ``grid_sample``'s zero padding
(with border padding, ``±inf`` is clamped to the border first and a NaN reads NaN, where
``grid_sample`` reads some vertex); a point far outside reads zero (unless its vertex
coordinate overflows to ±inf: NaN, as ``grid_sample``). The points' coordinates get no
gradient: where one is asked for, or numba is missing, :func:`interpolate` returns
``None`` and the caller uses ``grid_sample``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from eventrecon.errors import InputError
from eventrecon.sim.jit import (
    AVAILABLE,
    GRAIN,
    njit_borrowing,
    njit_inline,
    njit_parallel,
    parts,
    prange,
)

__all__ = ["channel_rows", "corners", "interpolate", "supported", "vertex_coords",
           "vertex_corners"]


def vertex_coords(coords: Tensor, sizes: tuple[int, ...], align_corners: bool,
                  padding: str) -> Tensor:
    """Normalised coordinates ``[N, d]`` in ``[-1, 1]`` → vertex units ``[N, d]``, by
    ``grid_sample``'s formulas: ``(c + 1)/2 · (R − 1)`` (``align_corners``) or
    ``((c + 1) R − 1)/2``; ``padding="border"`` clamps to ``[0, R − 1]``.

    >>> vertex_coords(torch.tensor([[-1.0], [1.0]]), (5,), True, "zeros").flatten().tolist()
    [0.0, 4.0]
    >>> vertex_coords(torch.tensor([[-1.0], [1.0]]), (5,), False, "zeros").flatten().tolist()
    [-0.5, 4.5]
    """
    res = torch.tensor(sizes, dtype=coords.dtype, device=coords.device)
    if align_corners:
        p = (coords + 1) / 2 * (res - 1)
    else:
        p = ((coords + 1) * res - 1) / 2
    if padding == "border":
        p = torch.minimum(p.clamp(min=0), res - 1)
    return p


def corners(p: Tensor) -> tuple[Tensor, Tensor]:
    """Vertex units ``p [N, d]`` → the lower corner ``i = ⌊p⌋ [N, d]`` (int64) and the
    weights ``[N, d, 2]``: ``(1 − (p − i), p − i)`` per axis, in ``p``'s dtype (so the
    compiled loops multiply in that dtype). A non-finite coordinate gets NaN weights (its
    point reads NaN) and a lower corner of −2, outside every grid, as a huge finite one
    does (which reads zero).

    >>> i, w = corners(torch.tensor([[1.25, float("nan")], [-1e30, 1e30]]))
    >>> i.tolist(), w[0, 0].tolist(), w[0, 1].isnan().tolist()
    ([[1, -2], [-2, 2147483648]], [0.75, 0.25], [True, True])
    """
    lo = torch.floor(p)
    frac = p - lo
    lower = torch.nan_to_num(lo, nan=-2.0, posinf=-2.0, neginf=-2.0).clamp(-2, 2 ** 31)
    return lower.long(), torch.stack([1 - frac, frac], dim=-1).contiguous()


@njit_borrowing
def _vertex_corners(coords: Any, axes: Any, sizes: Any, align: bool, border: bool,
                    units: Any, lower: Any, weights: Any) -> None:
    """:func:`vertex_coords` then :func:`corners`, point by point, of the columns
    ``axes`` of ``coords``, with their expressions in the coordinates' dtype (``sizes``:
    the vertex counts, and ``units``: 1, 2 and 2³¹, both in that dtype)."""
    one, two, top = units[0], units[1], units[2]
    zero = one - one
    for n in range(coords.shape[0]):
        for k in range(axes.shape[0]):
            c, r = coords[n, axes[k]], sizes[k]
            if align:
                p = (c + one) / two * (r - one)
            else:
                p = ((c + one) * r - one) / two
            if border:
                if p < zero:
                    p = zero
                if p > r - one:
                    p = r - one
            lo = np.floor(p)
            frac = p - lo
            if not math.isfinite(lo) or lo < -two:
                lower[n, k] = -2
            elif lo > top:
                lower[n, k] = 2 ** 31
            else:
                lower[n, k] = int(lo)
            weights[n, k, 0] = one - frac
            weights[n, k, 1] = frac


@njit_parallel
def _vertex_corners_parts(coords: Any, axes: Any, sizes: Any, align: bool, border: bool,
                          units: Any, lower: Any, weights: Any, p: int) -> None:
    """:func:`_vertex_corners` on ``p`` equal ranges of the points at once."""
    n = coords.shape[0]
    for k in prange(p):
        a, b = n * k // p, n * (k + 1) // p
        _vertex_corners(coords[a:b], axes, sizes, align, border, units, lower[a:b],
                        weights[a:b])


def vertex_corners(coords: Tensor, sizes: tuple[int, ...], align_corners: bool,
                   padding: str, axes: Sequence[int] | None = None) -> tuple[Tensor, Tensor]:
    """``corners(vertex_coords(coords[:, axes], …))``: normalised coordinates → the lower
    corner ``[N, d]`` (int64) and the weights ``[N, d, 2]`` of the ``d`` columns ``axes``
    (all of ``coords [N, d]`` when ``None``). On a CPU one compiled pass
    (:func:`_vertex_corners`) with the same expressions, so the same bits, where the
    tensor form takes a gather and a dozen passes over ``[N, d]``. The coordinates get
    no gradient.

    Raises:
        InputError: ``sizes`` and the columns read differ in number, or a column is
            outside ``coords``.
    """
    cols = list(range(coords.shape[1])) if axes is None else [int(a) for a in axes]
    if len(sizes) != len(cols) or not all(0 <= a < coords.shape[1] for a in cols):
        raise InputError("baselines.interp", "axes/sizes",
                         f"one size per column read, columns of [N, {coords.shape[1]}]",
                         f"axes {cols}, sizes {list(sizes)}")
    if not (AVAILABLE and coords.device.type == "cpu"
            and coords.dtype in (torch.float32, torch.float64)):
        picked = coords.detach() if axes is None else coords.detach()[:, cols]
        return corners(vertex_coords(picked, sizes, align_corners, padding))
    arr = coords.detach().contiguous().numpy()
    dtype = arr.dtype
    lower = torch.empty(coords.shape[0], len(cols), dtype=torch.long)
    weights = coords.new_empty(coords.shape[0], len(cols), 2)
    args = (arr, np.array(cols, dtype=np.int64), np.array(sizes, dtype=dtype),
            bool(align_corners), padding == "border",
            np.array([1.0, 2.0, 2.0 ** 31], dtype=dtype), lower.numpy(), weights.numpy())
    p = parts(arr.shape[0])
    if p == 1:
        _vertex_corners(*args)
    else:
        _vertex_corners_parts(*args, p)
    return lower, weights


@njit_inline
def _corner(sizes: Any, lower: Any, weights: Any, n: int, j: int) -> tuple[int, Any]:
    """Corner ``j`` of point ``n`` (bit ``d − 1 − k`` of ``j`` is its offset ``b_k`` along
    axis ``k``): its row in the grid flattened channel-last, ``Σ_k v_k Π_{l>k} R_l``, and
    its weight ``Π_k w_k(b_k)``; row −1 when it lies outside."""
    d = lower.shape[1]
    b = (j >> (d - 1)) & 1
    row = lower[n, 0] + b
    w = weights[n, 0, b]
    if row < 0 or row >= sizes[0]:
        return -1, w
    for k in range(1, d):
        b = (j >> (d - 1 - k)) & 1
        v = lower[n, k] + b
        if v < 0 or v >= sizes[k]:
            return -1, w
        row = row * sizes[k] + v
        w = w * weights[n, k, b]
    return row, w


@njit_borrowing
def _gather(table: Any, sizes: Any, lower: Any, weights: Any, out: Any) -> None:
    """``out[n] = Σ_j w_j table[row_j]`` over the corners of point ``n`` (compiled)."""
    c = table.shape[1]
    for n in range(lower.shape[0]):
        fill = 0.0
        for k in range(lower.shape[1]):
            if weights[n, k, 0] != weights[n, k, 0]:        # NaN: a non-finite coordinate
                fill = math.nan
        for ch in range(c):
            out[n, ch] = fill
        for j in range(1 << lower.shape[1]):
            row, w = _corner(sizes, lower, weights, n, j)
            if row >= 0:
                for ch in range(c):
                    out[n, ch] += w * table[row, ch]


@njit_borrowing
def _scatter(grad: Any, sizes: Any, lower: Any, weights: Any, table: Any) -> None:
    """``table[row_j] += w_j grad[n]``: the transpose of :func:`_gather` (compiled)."""
    c = table.shape[1]
    for n in range(lower.shape[0]):
        for j in range(1 << lower.shape[1]):
            row, w = _corner(sizes, lower, weights, n, j)
            if row >= 0:
                for ch in range(c):
                    table[row, ch] += w * grad[n, ch]


@njit_parallel
def _gather_parts(table: Any, sizes: Any, lower: Any, weights: Any, out: Any, p: int) -> None:
    """:func:`_gather` on ``p`` equal ranges of the points at once (the same values)."""
    n = lower.shape[0]
    for k in prange(p):
        a, b = n * k // p, n * (k + 1) // p
        _gather(table, sizes, lower[a:b], weights[a:b], out[a:b])


@njit_parallel
def _scatter_parts(grad: Any, sizes: Any, lower: Any, weights: Any, tables: Any) -> None:
    """:func:`_scatter` on ``P`` equal ranges of the points at once, range ``k`` into
    ``tables[k]`` (``[P, Π R, C]``; their sum over ``k`` is the gradient)."""
    n, p = lower.shape[0], tables.shape[0]
    for k in prange(p):
        a, b = n * k // p, n * (k + 1) // p
        _scatter(grad[a:b], sizes, lower[a:b], weights[a:b], tables[k])


def channel_rows(grid: Tensor) -> Tensor:
    """``grid [C, *R]`` → ``[Π R, C]``, channel-last rows (a view when the grid is stored
    channel-last, :func:`~baselines.grids.channels_last`)."""
    return grid.detach().movedim(0, -1).reshape(-1, grid.shape[0]).contiguous()


def _read(grid: Tensor, lower: Tensor, weights: Tensor) -> Tensor:
    """The forward pass: ``grid [C, *R]`` at the points' corners → ``[N, C]``; NaN for a
    point with a non-finite coordinate (as ``grid_sample`` with zero padding gives)."""
    out = grid.new_empty(lower.shape[0], grid.shape[0])
    sizes = torch.tensor(grid.shape[1:], dtype=torch.long)
    args = (channel_rows(grid).numpy(), sizes.numpy(), lower.numpy(), weights.numpy(),
            out.numpy())
    p = parts(lower.shape[0])
    if p == 1:
        _gather(*args)
    else:
        _gather_parts(*args, p)
    return out


class _Interpolate(torch.autograd.Function):
    """``(grid [C, *R], lower, weights) -> [N, C]``; the gradient reaches the grid only."""

    @staticmethod
    def forward(ctx: Any, grid: Tensor, lower: Tensor, weights: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(lower, weights)
        ctx.grid_shape = tuple(grid.shape)
        return _read(grid, lower, weights)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None, None]:  # type: ignore[override]
        lower, weights = ctx.saved_tensors
        c, *sizes = ctx.grid_shape
        rows = math.prod(sizes)
        # a copy of the gradient per range: worth it while the corners outnumber the rows
        p = parts(lower.shape[0], grain=max(GRAIN, rows >> lower.shape[1]))
        tables = grad.new_zeros(p, rows, c)                                # [P, Π R, C]
        args = (grad.contiguous().numpy(), torch.tensor(sizes, dtype=torch.long).numpy(),
                lower.numpy(), weights.numpy())
        if p == 1:
            _scatter(*args, tables[0].numpy())
            table = tables[0]
        else:
            _scatter_parts(*args, tables.numpy())
            table = tables.sum(0)
        return table.reshape(*sizes, c).movedim(-1, 0), None, None


def supported(grid: Tensor, coords: Tensor) -> bool:
    """Whether :func:`interpolate` serves this call: numba present, a grid of 1–3 axes on
    the CPU in float32/float64, coordinates of the same dtype that need no gradient."""
    return (AVAILABLE and grid.device.type == "cpu" and 2 <= grid.dim() <= 4
            and grid.dtype in (torch.float32, torch.float64) and coords.dtype == grid.dtype
            and not (coords.requires_grad and torch.is_grad_enabled()))


def interpolate(grid: Tensor, coords: Tensor, align_corners: bool = True,
                padding: str = "zeros", axes: Sequence[int] | None = None) -> Tensor | None:
    """Multilinear interpolation of ``grid [C, R_0, …]`` at normalised ``coords
    [N, d]`` (or at the columns ``axes`` of ``coords [N, D]``, one per grid axis) →
    ``[N, C]`` (channel-last), differentiable with respect to ``grid``; ``None`` where
    :func:`supported` is false (then use ``grid_sample``).

    Raises:
        InputError: ``coords`` is not ``[N, d]`` for the grid's ``d`` axes, or ``axes``
            does not name ``d`` of its columns.
    """
    d = grid.dim() - 1
    width = coords.shape[1] if coords.dim() == 2 else -1
    if coords.dim() != 2 or (axes is None and width != d) or (
            axes is not None and (len(axes) != d or not all(0 <= a < width for a in axes))):
        raise InputError("baselines.interp", "coords",
                         f"[N, {d}] (or [N, D] and {d} of its columns as axes) for a grid "
                         f"of shape {list(grid.shape)}",
                         f"{list(coords.shape)}, axes {None if axes is None else list(axes)}")
    if not supported(grid, coords):
        return None
    lower, weights = vertex_corners(coords, tuple(grid.shape[1:]), align_corners, padding,
                                    axes)
    if grid.requires_grad and torch.is_grad_enabled():
        return _Interpolate.apply(grid, lower, weights)
    return _read(grid, lower, weights)
