"""Multilinear interpolation of dense grids on the CPU, channel-last, with its gradient.

A grid ``G [C, R_0, …, R_{d-1}]`` (``d`` = 1, 2 or 3: the factorised backbones' lines
and planes) is read at ``N`` points given
in vertex units ``p [N, d]`` (:func:`vertex_coords`: ``p_k = i`` on vertex ``i``):

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
(numba), on one thread. At 13 000 points, forward and backward, a 128² plane of 32
channels takes 2.3 ms against 7.2 ms, a line 3.5–4.9× less (docs/results/history.md,
"Session 50"). Splitting the points between two threads was slower, as torch's OpenMP
workers keep spinning between ops.

The values are the corner gather's: ``grid_sample``'s up to the rounding of the weights.
A point with a non-finite coordinate reads NaN, as with ``grid_sample``'s zero padding
(with border padding, ``±inf`` is clamped to the border first and a NaN reads NaN, where
``grid_sample`` reads some vertex); a point far outside reads zero. The points'
coordinates get no gradient: where one is asked for, or numba is missing,
:func:`interpolate` returns ``None`` and the caller uses ``grid_sample``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch
from torch import Tensor

from eventrecon.errors import InputError
from eventrecon.sim.jit import AVAILABLE, njit_borrowing, njit_inline

__all__ = ["interpolate", "supported", "vertex_coords"]


def vertex_coords(coords: Tensor, sizes: tuple[int, ...], align_corners: bool,
                  padding: str) -> Tensor:
    """Normalised coordinates ``[N, d]`` in ``[-1, 1]`` → vertex units ``[N, d]``, by
    ``grid_sample``'s formulas: ``(c + 1)/2 · (R − 1)`` (``align_corners``) or
    ``((c + 1) R − 1)/2``; ``padding="border"`` clamps to ``[0, R − 1]``. The compiled
    loops compute the same per point, in float64 (:func:`_axis`); this is its reference.

    >>> vertex_coords(torch.tensor([[-1.0], [1.0]]), (5,), True, "zeros").flatten().tolist()
    [0.0, 4.0]
    >>> vertex_coords(torch.tensor([[-1.0], [1.0]]), (5,), False, "zeros").flatten().tolist()
    [-0.5, 4.5]
    """
    res = torch.tensor(sizes, dtype=coords.dtype)
    if align_corners:
        p = (coords + 1) / 2 * (res - 1)
    else:
        p = ((coords + 1) * res - 1) / 2
    if padding == "border":
        p = torch.minimum(p.clamp(min=0), res - 1)
    return p


@njit_inline
def _axis(c: float, size: int, align: bool, border: bool) -> tuple[int, float]:
    """One normalised coordinate → its lower vertex ``i = ⌊p⌋`` and fraction ``p − i``
    (:func:`vertex_coords`' ``p``, in float64). A non-finite ``p`` gives ``(−2, NaN)``:
    outside every grid, and a NaN that marks the point. A far ``p`` is held at ``−2`` or
    ``2^31`` (outside; its fraction is never used)."""
    if c != c:
        return -2, math.nan
    if align:
        p = (c + 1.0) * 0.5 * (size - 1)
    else:
        p = ((c + 1.0) * size - 1.0) * 0.5
    if border:
        p = min(max(p, 0.0), size - 1.0)
    if math.isinf(p):
        return -2, math.nan
    lo = min(max(math.floor(p), -2.0), 2.0 ** 31)
    return int(lo), p - lo


@njit_inline
def _point(coords: Any, n: int, sizes: Any, align: bool, border: bool, lower: Any,
           frac: Any) -> bool:
    """Fill ``lower[k]``, ``frac[k]`` for point ``n`` (:func:`_axis`); whether every
    coordinate is finite."""
    finite = True
    for k in range(coords.shape[1]):
        lower[k], frac[k] = _axis(coords[n, k], sizes[k], align, border)
        finite = finite and frac[k] == frac[k]
    return finite


@njit_inline
def _corner(sizes: Any, lower: Any, frac: Any, j: int) -> tuple[int, float]:
    """Corner ``j`` of the point in ``lower``, ``frac`` (bit ``d − 1 − k`` of ``j`` is its
    offset ``b_k`` along axis ``k``): its row in the grid flattened channel-last,
    ``Σ_k v_k Π_{l>k} R_l``, and its weight ``Π_k w_k(b_k)``; row −1 when outside."""
    d = lower.shape[0]
    row = 0
    w = 1.0
    for k in range(d):
        b = (j >> (d - 1 - k)) & 1
        v = lower[k] + b
        if v < 0 or v >= sizes[k]:
            return -1, w
        row = row * sizes[k] + v
        w = w * (frac[k] if b else 1.0 - frac[k])
    return row, w


@njit_borrowing
def _gather(table: Any, sizes: Any, coords: Any, align: bool, border: bool, lower: Any,
            frac: Any, weight: Any, out: Any) -> None:
    """``out[n] = Σ_j w_j table[row_j]`` over the corners of point ``n``; NaN for a point
    with a non-finite coordinate (compiled; ``lower``, ``frac``, ``weight``: scratch, the
    last in the table's dtype, which each weight is rounded to before use)."""
    c = table.shape[1]
    for n in range(coords.shape[0]):
        finite = _point(coords, n, sizes, align, border, lower, frac)
        for ch in range(c):
            out[n, ch] = 0.0 if finite else math.nan
        if not finite:
            continue
        for j in range(1 << coords.shape[1]):
            row, w = _corner(sizes, lower, frac, j)
            if row >= 0:
                weight[0] = w
                wt = weight[0]                              # in the table's dtype
                for ch in range(c):
                    out[n, ch] += wt * table[row, ch]


@njit_borrowing
def _scatter(grad: Any, sizes: Any, coords: Any, align: bool, border: bool, lower: Any,
             frac: Any, weight: Any, table: Any) -> None:
    """``table[row_j] += w_j grad[n]``: the transpose of :func:`_gather` (compiled)."""
    c = table.shape[1]
    for n in range(coords.shape[0]):
        if not _point(coords, n, sizes, align, border, lower, frac):
            continue
        for j in range(1 << coords.shape[1]):
            row, w = _corner(sizes, lower, frac, j)
            if row >= 0:
                weight[0] = w
                wt = weight[0]
                for ch in range(c):
                    table[row, ch] += wt * grad[n, ch]


def _table(grid: Tensor) -> Tensor:
    """``grid [C, *R]`` → ``[Π R, C]``, channel-last rows (a view when the grid is stored
    channel-last, :func:`~baselines.grids.channels_last`)."""
    return grid.detach().movedim(0, -1).reshape(-1, grid.shape[0]).contiguous()


def _args(grid_shape: tuple[int, ...], coords: Tensor, align_corners: bool, padding: str,
          dtype: torch.dtype) -> tuple[Any, ...]:
    """The compiled loops' arguments after the table or gradient: sizes, coordinates,
    the convention and the scratch arrays."""
    d = len(grid_shape) - 1
    return (np.asarray(grid_shape[1:], dtype=np.int64), coords.contiguous().numpy(),
            bool(align_corners), padding == "border", np.empty(d, np.int64),
            np.empty(d, np.float64), torch.empty(1, dtype=dtype).numpy())


class _Interpolate(torch.autograd.Function):
    """``(grid [C, *R], coords [N, d]) -> [N, C]``; the gradient reaches the grid only."""

    @staticmethod
    def forward(ctx: Any, grid: Tensor, coords: Tensor, align_corners: bool,  # type: ignore[override]
                padding: str) -> Tensor:
        ctx.save_for_backward(coords)
        ctx.convention = (tuple(grid.shape), align_corners, padding)
        return _read(grid, coords, align_corners, padding)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        (coords,) = ctx.saved_tensors
        shape, align_corners, padding = ctx.convention
        c, *sizes = shape
        table = grad.new_zeros(math.prod(sizes), c)                      # [Π R, C]
        _scatter(grad.contiguous().numpy(),
                 *_args(shape, coords, align_corners, padding, grad.dtype), table.numpy())
        return table.reshape(*sizes, c).movedim(-1, 0), None, None, None


def _read(grid: Tensor, coords: Tensor, align_corners: bool, padding: str) -> Tensor:
    """The forward pass: ``grid [C, *R]`` at the points ``coords [N, d]`` → ``[N, C]``."""
    out = grid.new_empty(coords.shape[0], grid.shape[0])
    _gather(_table(grid).numpy(), *_args(tuple(grid.shape), coords, align_corners, padding,
                                         grid.dtype), out.numpy())
    return out


def supported(grid: Tensor, coords: Tensor) -> bool:
    """Whether :func:`interpolate` serves this call: numba present, a grid of 1–3 axes on
    the CPU in float32/float64, coordinates of the same dtype that need no gradient."""
    return (AVAILABLE and grid.device.type == "cpu" and 2 <= grid.dim() <= 4
            and grid.dtype in (torch.float32, torch.float64) and coords.dtype == grid.dtype
            and not (coords.requires_grad and torch.is_grad_enabled()))


def interpolate(grid: Tensor, coords: Tensor, align_corners: bool = True,
                padding: str = "zeros") -> Tensor | None:
    """Multilinear interpolation of ``grid [C, R_0, …]`` at normalised ``coords
    [N, d]`` → ``[N, C]`` (channel-last), differentiable with respect to ``grid``;
    ``None`` where :func:`supported` is false (then use ``grid_sample``).

    Raises:
        InputError: ``coords`` is not ``[N, d]`` for the grid's ``d`` axes.
    """
    if coords.dim() != 2 or coords.shape[1] != grid.dim() - 1:
        raise InputError("baselines.interp", "coords",
                         f"[N, {grid.dim() - 1}] for a grid of shape {list(grid.shape)}",
                         list(coords.shape))
    if not supported(grid, coords):
        return None
    coords = coords.detach()
    if grid.requires_grad and torch.is_grad_enabled():
        return _Interpolate.apply(grid, coords, align_corners, padding)
    return _read(grid, coords, align_corners, padding)
