"""TensoRF-CP's rank sum of four line products, fused on the CPU, with its gradient.

For lines ``T_a [R_a, C]`` (``a = x, y, z, t``, channels innermost, ``C = F·R``) read at
a point with lower vertex ``i_a`` and weights ``(u_a, v_a)`` (:func:`baselines.interp.corners`;
a vertex outside the line adds nothing),

.. math::
    s_a[c] = u_a T_a[i_a, c] + v_a T_a[i_a + 1, c],\\qquad
    o_f = \\sum_{r=0}^{R-1} ((s_x s_y) s_z) s_t\\,[fR + r],

and the gradient of a loss ``L`` with respect to the lines is the scatter

.. math::
    \\frac{\\partial L}{\\partial T_a[i_a + b, c]} \\mathrel{+}= w_{a,b}\\,
    \\frac{\\partial L}{\\partial o_{f(c)}} \\prod_{a' \\ne a} s_{a'}[c].

Why: sampled line by line (:mod:`baselines.interp`) the four samples and the three
products are ``[N, C]`` tensors that stream through memory (at 39 040 points and
``C = 64``, 10 MB each): the products and their gradients were ~16 of ~30 ms of the
fields' forward and backward. Here one compiled loop per pass reads the four small lines
(in cache) and writes ``[N, F]``; the samples are recomputed in the backward pass.

The samples and products are computed with the same expressions, in the same order, as
line-by-line sampling followed by ``s_x * s_y * s_z * s_t`` and autograd's products, so
the lines' gradients are the same to the bit; the forward's rank sum runs in another
order than ``Tensor.sum``, so ``o`` agrees to rounding. A point with a non-finite
coordinate reads NaN there, as line by line. Where :func:`supported` is false (a GPU, no
numba, coordinates that need a gradient) :func:`cp_rank_sum` returns ``None`` and the
caller samples line by line.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from baselines.interp import corners, vertex_coords
from eventrecon.sim.jit import AVAILABLE, njit_borrowing, njit_inline

__all__ = ["cp_rank_sum", "supported"]


@njit_inline
def _pair(lower: Any, weights: Any, sizes: Any, n: int, a: int) -> tuple[int, int, Any, Any,
                                                                            bool, bool]:
    """Point ``n``'s two vertices on line ``a``: rows to read (0 for a vertex outside),
    their weights (0 for a vertex outside, NaN kept) and whether each lies inside."""
    i = lower[n, a]
    u, v = weights[n, a, 0], weights[n, a, 1]
    inside_u = 0 <= i < sizes[a]
    inside_v = 0 <= i + 1 < sizes[a]
    if not inside_u and u == u:                  # u − u: a zero of the weights' dtype
        u = u - u
    if not inside_v and v == v:
        v = v - v
    return (i if inside_u else 0), (i + 1 if inside_v else 0), u, v, inside_u, inside_v


@njit_borrowing
def _forward(T0: Any, T1: Any, T2: Any, T3: Any, sizes: Any, lower: Any, weights: Any,
             rank: int, out: Any, prod: Any) -> None:
    """``out [N, F]``: the rank sums of the line products (module docstring)."""
    c_all = T0.shape[1]
    for n in range(lower.shape[0]):
        a0, b0, u0, v0, _, _ = _pair(lower, weights, sizes, n, 0)
        a1, b1, u1, v1, _, _ = _pair(lower, weights, sizes, n, 1)
        a2, b2, u2, v2, _, _ = _pair(lower, weights, sizes, n, 2)
        a3, b3, u3, v3, _, _ = _pair(lower, weights, sizes, n, 3)
        for c in range(c_all):
            s0 = u0 * T0[a0, c] + v0 * T0[b0, c]
            s1 = u1 * T1[a1, c] + v1 * T1[b1, c]
            s2 = u2 * T2[a2, c] + v2 * T2[b2, c]
            s3 = u3 * T3[a3, c] + v3 * T3[b3, c]
            prod[c] = ((s0 * s1) * s2) * s3
        for f in range(c_all // rank):
            acc = prod[f * rank]
            for r in range(1, rank):
                acc += prod[f * rank + r]
            out[n, f] = acc


@njit_inline
def _axpy(G: Any, row: int, w: Any, x: Any, a: int) -> None:
    """``G[row] += w · x[a]`` over the channels."""
    for c in range(G.shape[1]):
        G[row, c] += w * x[a, c]


@njit_borrowing
def _backward(T0: Any, T1: Any, T2: Any, T3: Any, sizes: Any, lower: Any, weights: Any,
              rank: int, grad: Any, G0: Any, G1: Any, G2: Any, G3: Any, part: Any) -> None:
    """``G_a += ∂L/∂T_a`` for ``grad = ∂L/∂out [N, F]`` (module docstring); ``part
    [4, C]`` scratch. The products' gradients follow autograd's order for
    ``((s0 · s1) · s2) · s3``."""
    c_all = T0.shape[1]
    for n in range(lower.shape[0]):
        a0, b0, u0, v0, in_a0, in_b0 = _pair(lower, weights, sizes, n, 0)
        a1, b1, u1, v1, in_a1, in_b1 = _pair(lower, weights, sizes, n, 1)
        a2, b2, u2, v2, in_a2, in_b2 = _pair(lower, weights, sizes, n, 2)
        a3, b3, u3, v3, in_a3, in_b3 = _pair(lower, weights, sizes, n, 3)
        for f in range(c_all // rank):
            g = grad[n, f]
            for c in range(f * rank, f * rank + rank):
                s0 = u0 * T0[a0, c] + v0 * T0[b0, c]
                s1 = u1 * T1[a1, c] + v1 * T1[b1, c]
                s2 = u2 * T2[a2, c] + v2 * T2[b2, c]
                s3 = u3 * T3[a3, c] + v3 * T3[b3, c]
                p01 = s0 * s1
                g012 = g * s3
                g01 = g012 * s2
                part[3, c] = g * (p01 * s2)
                part[2, c] = g012 * p01
                part[1, c] = g01 * s0
                part[0, c] = g01 * s1
        if in_a0:
            _axpy(G0, a0, u0, part, 0)
        if in_b0:
            _axpy(G0, b0, v0, part, 0)
        if in_a1:
            _axpy(G1, a1, u1, part, 1)
        if in_b1:
            _axpy(G1, b1, v1, part, 1)
        if in_a2:
            _axpy(G2, a2, u2, part, 2)
        if in_b2:
            _axpy(G2, b2, v2, part, 2)
        if in_a3:
            _axpy(G3, a3, u3, part, 3)
        if in_b3:
            _axpy(G3, b3, v3, part, 3)


def _table(line: Tensor) -> np.ndarray:
    """``line [C, R]`` → ``[R, C]`` rows (a view of a channel-last line)."""
    return line.detach().t().contiguous().numpy()


class _CPRankSum(torch.autograd.Function):
    """``(T_x, T_y, T_z, T_t [C, R_a], lower, weights, rank) -> [N, F]``; gradients reach
    the lines only."""

    @staticmethod
    def forward(ctx: Any, l0: Tensor, l1: Tensor, l2: Tensor, l3: Tensor, lower: Tensor,  # type: ignore[override]
                weights: Tensor, rank: int) -> Tensor:
        lines = (l0, l1, l2, l3)
        ctx.save_for_backward(*lines, lower, weights)
        ctx.rank = rank
        return _read(lines, lower, weights, rank)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        *lines, lower, weights = ctx.saved_tensors
        tables = [_table(line) for line in lines]
        sums = [torch.zeros(t.shape, dtype=lines[0].dtype) for t in tables]     # [R_a, C]
        part = np.empty((4, tables[0].shape[1]), tables[0].dtype)
        _backward(*tables, _sizes(lines), lower.numpy(), weights.numpy(), ctx.rank,
                  grad.contiguous().numpy(), *(s.numpy() for s in sums), part)
        return (*(s.t() for s in sums), None, None, None)


def _sizes(lines: Sequence[Tensor]) -> np.ndarray:
    return np.array([line.shape[1] for line in lines], dtype=np.int64)


def _read(lines: Sequence[Tensor], lower: Tensor, weights: Tensor, rank: int) -> Tensor:
    """The forward pass: ``[N, F]``."""
    c = lines[0].shape[0]
    out = lines[0].new_empty(lower.shape[0], c // rank)
    prod = np.empty(c, out.numpy().dtype)
    _forward(*(_table(line) for line in lines), _sizes(lines), lower.numpy(), weights.numpy(),
             rank, out.numpy(), prod)
    return out


def supported(lines: Sequence[Tensor], coords: Tensor, align_corners: Sequence[bool]) -> bool:
    """Whether :func:`cp_rank_sum` serves this call: numba present, four lines ``[C, R_a]``
    of one float32/float64 dtype on the CPU, one sampling convention, coordinates of that
    dtype that need no gradient."""
    return (AVAILABLE and len(lines) == 4 and all(line.dim() == 2 for line in lines)
            and len(set(align_corners)) == 1
            and all(line.device.type == "cpu" and line.dtype == coords.dtype
                    for line in lines)
            and coords.dtype in (torch.float32, torch.float64)
            and coords.device.type == "cpu"
            and not (coords.requires_grad and torch.is_grad_enabled()))


def cp_rank_sum(lines: Sequence[Tensor], coords: Tensor, align_corners: Sequence[bool],
                padding: str, rank: int) -> Tensor | None:
    """``o [N, F]`` (module docstring) of the lines ``[C, R_a]`` at ``coords [N, 4]``
    (``[-1, 1]``, the lines' axes in order), differentiable with respect to the lines;
    ``None`` where :func:`supported` is false."""
    if not supported(lines, coords, align_corners):
        return None
    sizes = tuple(int(line.shape[1]) for line in lines)
    p = vertex_coords(coords.detach(), sizes, align_corners[0], padding)
    lower, weights = corners(p)
    if torch.is_grad_enabled() and any(line.requires_grad for line in lines):
        return _CPRankSum.apply(*lines, lower, weights, int(rank))
    return _read(lines, lower, weights, int(rank))
