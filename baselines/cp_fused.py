"""TensoRF-CP's rank sum of four line products, fused on the CPU, with its gradient.

For lines ``T_a [R_a, C]`` (``a = x, y, z, t``, channels innermost, ``C = F·R``) read at
a point with lower vertex ``i_a`` and weights ``(u_a, v_a)`` (:func:`baselines.interp.corners`;
a vertex outside the line is not read),

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
With two or more torch threads the points are split into ranges run on numba's threads
(:func:`eventrecon.sim.jit.parts`), each range scattering into its own copy of the lines'
gradients, summed at the end.

The samples and products are computed with the same expressions, in the same order, as
line-by-line sampling followed by ``s_x * s_y * s_z * s_t`` and autograd's products, so
on one thread the lines' gradients are the same to the bit (split between threads, to
the rounding of the ranges' sum); the forward's rank sum runs in another
order than ``Tensor.sum``, so ``o`` agrees to rounding. A point with a non-finite
coordinate reads NaN there, as line by line. The backward pass reads the lines again, so
a line changed in place between the passes raises autograd's version error. Where
:func:`supported` is false (a GPU, no numba, coordinates that need a gradient)
:func:`cp_rank_sum` returns ``None`` and the caller samples line by line.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from baselines.fused_kernels import (
    PAD,
    axpy,
    line_sample,
    line_vertices,
    rank_sums,
    run_forward,
    scatter_copies,
    supported_factors,
)
from baselines.interp import channel_rows, vertex_corners
from eventrecon.errors import InputError
from eventrecon.sim.jit import njit_borrowing, njit_inline, njit_parallel, prange

__all__ = ["cp_rank_sum", "supported"]


@njit_inline
def _samples(T0: Any, T1: Any, T2: Any, T3: Any, sizes: Any, lower: Any, weights: Any,
             n: int, s: Any) -> tuple:
    """Point ``n``'s four line samples into ``s [4, C]``; returns each line's vertices
    (rows, weights, inside) for the scatter."""
    a0, b0, u0, v0, in_a0, in_b0 = line_vertices(lower, weights, sizes, n, 0)
    a1, b1, u1, v1, in_a1, in_b1 = line_vertices(lower, weights, sizes, n, 1)
    a2, b2, u2, v2, in_a2, in_b2 = line_vertices(lower, weights, sizes, n, 2)
    a3, b3, u3, v3, in_a3, in_b3 = line_vertices(lower, weights, sizes, n, 3)
    line_sample(T0, a0, b0, u0, v0, in_a0, in_b0, s, 0)
    line_sample(T1, a1, b1, u1, v1, in_a1, in_b1, s, 1)
    line_sample(T2, a2, b2, u2, v2, in_a2, in_b2, s, 2)
    line_sample(T3, a3, b3, u3, v3, in_a3, in_b3, s, 3)
    return ((a0, b0, u0, v0, in_a0, in_b0), (a1, b1, u1, v1, in_a1, in_b1),
            (a2, b2, u2, v2, in_a2, in_b2), (a3, b3, u3, v3, in_a3, in_b3))


@njit_borrowing
def _forward(T0: Any, T1: Any, T2: Any, T3: Any, sizes: Any, lower: Any, weights: Any,
             rank: int, out: Any, s: Any, prod: Any) -> None:
    """``out [N, F]``: the rank sums of the line products (module docstring,
    :func:`~baselines.fused_kernels.rank_sums`); ``s [4, C]`` and ``prod [C]`` scratch."""
    c_all = T0.shape[1]
    for n in range(lower.shape[0]):
        _samples(T0, T1, T2, T3, sizes, lower, weights, n, s)
        for c in range(c_all):
            prod[c] = ((s[0, c] * s[1, c]) * s[2, c]) * s[3, c]
        rank_sums(prod, rank, c_all, out, n)


@njit_borrowing
def _backward(T0: Any, T1: Any, T2: Any, T3: Any, sizes: Any, lower: Any, weights: Any,
              feature: Any, grad: Any, G0: Any, G1: Any, G2: Any, G3: Any, s: Any,
              part: Any) -> None:
    """``G_a += ∂L/∂T_a`` for ``grad = ∂L/∂out [N, F]`` (module docstring); ``feature
    [C]``: each channel's feature ``f(c)``; ``s [4, C]``, ``part [5, C]`` scratch. The
    products' gradients follow autograd's order for ``((s0 · s1) · s2) · s3``.

    Each of ``part``'s rows is written by a loop over all ``C`` channels that writes
    nothing else: LLVM vectorises such a loop, but not one that writes four rows
    (too many pairs of rows to check for overlap) nor one of ``R < 16`` channels."""
    c_all = T0.shape[1]
    s0, s1, s2, s3 = s[0], s[1], s[2], s[3]
    q0, q1, q2, q3, g = part[0], part[1], part[2], part[3], part[4]
    for n in range(lower.shape[0]):
        p0, p1, p2, p3 = _samples(T0, T1, T2, T3, sizes, lower, weights, n, s)
        row = grad[n]
        for c in range(c_all):
            g[c] = row[feature[c]]
        for c in range(c_all):
            q3[c] = g[c] * ((s0[c] * s1[c]) * s2[c])
        for c in range(c_all):
            q2[c] = (g[c] * s3[c]) * (s0[c] * s1[c])
        for c in range(c_all):
            q1[c] = ((g[c] * s3[c]) * s2[c]) * s0[c]
        for c in range(c_all):
            q0[c] = ((g[c] * s3[c]) * s2[c]) * s1[c]
        for G, p, k in ((G0, p0, 0), (G1, p1, 1), (G2, p2, 2), (G3, p3, 3)):
            axpy(G, p[0], p[2], part, k, p[4])
            axpy(G, p[1], p[3], part, k, p[5])


@njit_parallel
def _forward_parts(T0: Any, T1: Any, T2: Any, T3: Any, sizes: Any, lower: Any, weights: Any,
                   rank: int, out: Any, s: Any, prod: Any) -> None:
    """:func:`_forward` on ``P`` equal ranges of the points at once, ``s [P, 4, C]`` and
    ``prod [P, C]`` each range's scratch (the same values)."""
    n, p = lower.shape[0], s.shape[0]
    for k in prange(p):
        a, b = n * k // p, n * (k + 1) // p
        _forward(T0, T1, T2, T3, sizes, lower[a:b], weights[a:b], rank, out[a:b], s[k],
                 prod[k])


@njit_parallel
def _backward_parts(T0: Any, T1: Any, T2: Any, T3: Any, sizes: Any, lower: Any, weights: Any,
                    feature: Any, grad: Any, G0: Any, G1: Any, G2: Any, G3: Any, s: Any,
                    part: Any) -> None:
    """:func:`_backward` on ``P`` equal ranges of the points at once, range ``k`` into its
    own ``G_a[k]`` (``G_a [P, R_a, C]``; their sum over ``k`` is the gradient) with
    scratch ``s[k] [4, C]``, ``part[k] [5, C]``."""
    n, p = lower.shape[0], s.shape[0]
    for k in prange(p):
        a, b = n * k // p, n * (k + 1) // p
        _backward(T0, T1, T2, T3, sizes, lower[a:b], weights[a:b], feature, grad[a:b], G0[k],
                  G1[k], G2[k], G3[k], s[k], part[k])


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
        tables = [channel_rows(line).numpy() for line in lines]
        # [P, R_a, C] each; a point writes 2 rows of each of the 4 lines
        sums = scatter_copies(lower.shape[0], tables, lines[0].dtype, corners=4 * 2)
        p = sums[0].shape[0]
        c, dtype = tables[0].shape[1], tables[0].dtype
        samples = np.empty((p, 4, c + PAD), dtype)
        part = np.empty((p, 5, c + PAD), dtype)
        feature = np.arange(c, dtype=np.int64) // ctx.rank
        args = (*tables, _sizes(lines), lower.numpy(), weights.numpy(), feature,
                grad.contiguous().numpy())
        if p == 1:
            _backward(*args, *(s[0].numpy() for s in sums), samples[0], part[0])
            return (*(s[0].t() for s in sums), None, None, None)
        _backward_parts(*args, *(s.numpy() for s in sums), samples, part)
        return (*(s.sum(0).t() for s in sums), None, None, None)


def _sizes(lines: Sequence[Tensor]) -> np.ndarray:
    """``[4]`` int64: each line's vertex count."""
    return np.array([line.shape[1] for line in lines], dtype=np.int64)


def _read(lines: Sequence[Tensor], lower: Tensor, weights: Tensor, rank: int) -> Tensor:
    """The forward pass: ``[N, F]``."""
    c = lines[0].shape[0]
    out = lines[0].new_empty(lower.shape[0], c // rank)
    args = (*(channel_rows(line).numpy() for line in lines), _sizes(lines), lower.numpy(),
            weights.numpy(), rank, out.numpy())
    run_forward(_forward, _forward_parts, args, lower.shape[0], 4, c, out.numpy().dtype)
    return out


def supported(lines: Sequence[Tensor], coords: Tensor, align_corners: Sequence[bool]) -> bool:
    """Whether :func:`cp_rank_sum` serves this call: numba present, four lines ``[C, R_a]``
    of one ``C`` and one float32/float64 dtype on the CPU, one sampling convention,
    coordinates ``[N, 4]`` of that dtype that need no gradient."""
    return (len(lines) == 4 and all(line.dim() == 2 for line in lines)
            and len(set(align_corners)) == 1 and supported_factors(list(lines), coords))


def cp_rank_sum(lines: Sequence[Tensor], coords: Tensor, align_corners: Sequence[bool],
                padding: str, rank: int) -> Tensor | None:
    """``o [N, F]`` (module docstring) of the lines ``[C, R_a]`` at ``coords [N, 4]``
    (``[-1, 1]``, the lines' axes in order), differentiable with respect to the lines;
    ``None`` where :func:`supported` is false."""
    if not supported(lines, coords, align_corners):
        return None
    if rank < 1 or lines[0].shape[0] % rank:
        raise InputError("baselines.cp_fused", "rank",
                         f"a divisor of the lines' {lines[0].shape[0]} channels", rank)
    sizes = tuple(int(line.shape[1]) for line in lines)
    lower, weights = vertex_corners(coords, sizes, align_corners[0], padding)
    if torch.is_grad_enabled() and any(line.requires_grad for line in lines):
        return _CPRankSum.apply(*lines, lower, weights, int(rank))
    return _read(lines, lower, weights, int(rank))
