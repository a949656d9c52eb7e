"""Multilinear interpolation of lines and planes on the CPU, channel-last, with its gradient.

A factor grid ``G [C, R_0, …, R_{d-1}]`` (``d`` = 1 or 2) is read at ``N`` points given
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
contiguous row of ``C`` values per vertex; the factors are stored so,
:func:`~baselines.grids.channels_last`) by compiled loops (numba), on one thread: at
13 000 points, forward and backward, a 128² plane of 32 channels takes 2.3 ms against
7.2 ms, a line 3.5–4.9× less (docs/results/history.md, "Session 50"; splitting the points
between two threads was slower, as torch's OpenMP workers keep spinning between ops).
The values are the corner gather's, equal to ``grid_sample``'s up to the rounding of the
weights. The points' coordinates get no gradient: where one is asked for, or numba is
missing, :func:`interpolate` returns ``None`` and the caller uses ``grid_sample``.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from eventrecon.sim.jit import AVAILABLE, njit_borrowing

__all__ = ["corners", "interpolate", "supported", "vertex_coords"]


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
    res = torch.tensor(sizes, dtype=coords.dtype)
    if align_corners:
        p = (coords + 1) / 2 * (res - 1)
    else:
        p = ((coords + 1) * res - 1) / 2
    if padding == "border":
        p = torch.minimum(p.clamp(min=0), res - 1)
    return p.contiguous()


def corners(p: Tensor) -> tuple[Tensor, Tensor]:
    """Vertex units ``p [N, d]`` → the lower corner ``i = ⌊p⌋ [N, d]`` (int64) and the
    weights ``[N, d, 2]``: ``(1 − (p − i), p − i)`` per axis, in ``p``'s dtype (so the
    compiled loops multiply in that dtype). A non-finite ``p`` gives a corner far outside,
    which reads nothing.

    >>> i, w = corners(torch.tensor([[1.25]]))
    >>> i.tolist(), w.tolist()
    ([[1]], [[[0.75, 0.25]]])
    """
    lo = torch.floor(p)
    f = p - lo
    i = torch.nan_to_num(lo, nan=-2.0, posinf=-2.0, neginf=-2.0).clamp(-2, 2 ** 40).long()
    return i.contiguous(), torch.stack([1 - f, f], dim=-1).contiguous()


@njit_borrowing
def _gather1(table: Any, idx: Any, wts: Any, out: Any) -> None:   # pragma: no cover
    """``out[n] = Σ_b w_b table[i + b]`` for a line ``table [R, C]`` (compiled)."""
    r, c = table.shape
    for n in range(idx.shape[0]):
        for ch in range(c):
            out[n, ch] = 0.0
        for b in range(2):
            j = idx[n, 0] + b
            if j < 0 or j >= r:
                continue
            w = wts[n, 0, b]
            for ch in range(c):
                out[n, ch] += w * table[j, ch]


@njit_borrowing
def _scatter1(grad: Any, idx: Any, wts: Any, gtable: Any) -> None:   # pragma: no cover
    """``gtable[i + b] += w_b grad[n]``: the transpose of :func:`_gather1` (compiled)."""
    r, c = gtable.shape
    for n in range(idx.shape[0]):
        for b in range(2):
            j = idx[n, 0] + b
            if j < 0 or j >= r:
                continue
            w = wts[n, 0, b]
            for ch in range(c):
                gtable[j, ch] += w * grad[n, ch]


@njit_borrowing
def _gather2(table: Any, idx: Any, wts: Any, out: Any) -> None:   # pragma: no cover
    """``out[n] = Σ_b w_b table[i_0 + b_0, i_1 + b_1]`` for a plane ``table [R_0, R_1, C]``
    (compiled)."""
    r0, r1, c = table.shape
    for n in range(idx.shape[0]):
        for ch in range(c):
            out[n, ch] = 0.0
        for b0 in range(2):
            j0 = idx[n, 0] + b0
            if j0 < 0 or j0 >= r0:
                continue
            for b1 in range(2):
                j1 = idx[n, 1] + b1
                if j1 < 0 or j1 >= r1:
                    continue
                w = wts[n, 0, b0] * wts[n, 1, b1]
                for ch in range(c):
                    out[n, ch] += w * table[j0, j1, ch]


@njit_borrowing
def _scatter2(grad: Any, idx: Any, wts: Any, gtable: Any) -> None:   # pragma: no cover
    """``gtable[i_0 + b_0, i_1 + b_1] += w_b grad[n]``: the transpose of :func:`_gather2`
    (compiled)."""
    r0, r1, c = gtable.shape
    for n in range(idx.shape[0]):
        for b0 in range(2):
            j0 = idx[n, 0] + b0
            if j0 < 0 or j0 >= r0:
                continue
            for b1 in range(2):
                j1 = idx[n, 1] + b1
                if j1 < 0 or j1 >= r1:
                    continue
                w = wts[n, 0, b0] * wts[n, 1, b1]
                for ch in range(c):
                    gtable[j0, j1, ch] += w * grad[n, ch]


_KERNELS = {1: (_gather1, _scatter1), 2: (_gather2, _scatter2)}


def _gather(grid: Tensor, idx: Tensor, wts: Tensor) -> Tensor:
    """The forward pass: ``grid [C, *R]`` read at the corners → ``[N, C]``."""
    table = grid.detach().movedim(0, -1).contiguous()              # [*R, C]: a view
    out = grid.new_empty(idx.shape[0], grid.shape[0])
    _KERNELS[grid.dim() - 1][0](table.numpy(), idx.numpy(), wts.numpy(), out.numpy())
    return out


def _scatter(grad: Tensor, idx: Tensor, wts: Tensor, shape: tuple[int, ...]) -> Tensor:
    """The backward pass: ``grad [N, C]`` → the grid's gradient ``[C, *R]``, with
    channel-last strides (:func:`~baselines.grids.channels_last`)."""
    table = grad.new_zeros(*shape[1:], shape[0])                    # [*R, C]
    _KERNELS[len(shape) - 1][1](grad.contiguous().numpy(), idx.numpy(), wts.numpy(),
                               table.numpy())
    return table.movedim(-1, 0)


class _Interpolate(torch.autograd.Function):
    """``(grid [C, *R], idx, wts) -> [N, C]``; the gradient reaches the grid only."""

    @staticmethod
    def forward(ctx: Any, grid: Tensor, idx: Tensor, wts: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(idx, wts)
        ctx.grid_shape = tuple(grid.shape)
        return _gather(grid, idx, wts)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None, None]:  # type: ignore[override]
        idx, wts = ctx.saved_tensors
        return _scatter(grad, idx, wts, ctx.grid_shape), None, None


def supported(grid: Tensor, coords: Tensor) -> bool:
    """Whether :func:`interpolate` serves this call: numba present, a line or plane on
    the CPU in float32/float64, coordinates of the same dtype that need no gradient."""
    return (AVAILABLE and grid.device.type == "cpu" and grid.dim() in (2, 3)
            and grid.dtype in (torch.float32, torch.float64) and coords.dtype == grid.dtype
            and not (coords.requires_grad and torch.is_grad_enabled()))


def interpolate(grid: Tensor, coords: Tensor, align_corners: bool = True,
                padding: str = "zeros") -> Tensor | None:
    """Multilinear interpolation of ``grid [C, R_0(, R_1)]`` at normalised ``coords
    [N, d]`` → ``[N, C]`` (channel-last), differentiable with respect to ``grid``;
    ``None`` where :func:`supported` is false (then use ``grid_sample``)."""
    if not supported(grid, coords):
        return None
    p = vertex_coords(coords.detach(), tuple(grid.shape[1:]), align_corners, padding)
    idx, wts = corners(p)
    if grid.requires_grad and torch.is_grad_enabled():
        return _Interpolate.apply(grid, idx, wts)
    return _gather(grid, idx, wts)
