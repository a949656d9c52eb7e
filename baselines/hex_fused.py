"""HexPlane's rank sum of three plane · plane · line products, fused on the CPU, with its
gradient.

For the spatial planes ``P_k``, the space-time planes ``Q_k`` and the lines ``V_k``
(``k = 0, 1, 2``; channels innermost, ``C = F·R``), each sampled at a point as
:mod:`baselines.interp` samples it (bilinear over the plane's four corners, linear over
the line's two; a corner outside is not read),

.. math::
    o_f = \\sum_{r=0}^{R-1} \\Big(\\big((P_0 Q_0) V_0 + (P_1 Q_1) V_1\\big)
          + (P_2 Q_2) V_2\\Big)[fR + r],

and the gradient of a loss ``L`` reaches each factor as the scatter of its sample's
gradient over its corners, with the products' gradients in autograd's order for
``(P_k · Q_k) · V_k``:
``∂L/∂V_k = g (P_k Q_k)``, ``∂L/∂P_k = (g V_k) Q_k``, ``∂L/∂Q_k = (g V_k) P_k``,
``g[c] = ∂L/∂o_{f(c)}``.

Why: sampled factor by factor, the nine samples, the products and their gradients are
``[N, C]`` tensors that stream through memory, plus nine corner passes over the
coordinates. Here one compiled loop per pass reads the factors (at the CPU size, 48
vertices per axis and 32 channels, all nine fit in 1.4 MB) and writes ``[N, F]``; the
corners come from two passes over the coordinates (one per sampling convention), and the
samples are recomputed in the backward pass. With two or more torch threads the points
are split into ranges run on numba's threads, each range scattering into its own copy
of the factors' gradients, summed at the end.

The samples and products are computed with the same expressions, in the same order, as
factor-by-factor sampling followed by :meth:`baselines.hexplane.HexPlaneField.combine`,
so on one thread the factors' gradients are the same to the bit (split between threads,
to the rounding of the ranges' sum); the forward's rank sum runs in another order than
``Tensor.sum``, so ``o`` agrees to rounding. Where :func:`supported` is false (a GPU, no
numba, coordinates that need a gradient, factors of other shapes, or factors too large
to stay in cache: :data:`MAX_BYTES`, the authors' 500² planes among them)
:func:`hex_rank_sum` returns ``None`` and the caller samples factor by factor.
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

__all__ = ["hex_rank_sum", "supported"]

#: Points per block of the backward pass (:func:`_backward`).
BLOCK = 64
#: The fused pass serves factors of at most this many bytes in all: every point reads all
#: nine, so they must stay near the core. On the 2-core Zen 4 EPYC (1 MB L2 per core), at
#: 13 605 points along rays, rank 8, two threads, forward and backward: 5.4–5.7 against
#: 9.3–10.5 ms at 64 vertices per axis (2.2 MB of factors), 6.6–10.7 against 9.3–14.3 at 96
#: (4.4 MB), 14.3–18.5 against 14.5–15.0 at 128 (7.5 MB), 30–32 against 16–21 at 256
#: (docs/results/history.md, "Session 63"). Larger factors are sampled one by one. The
#: bound applies to the factors as read: the density's leading channels alone (the
#: occupancy grid's queries) count a quarter of the bytes (their compact copy is what the
#: pass reads; not measured apart).
MAX_BYTES = 6 << 20


@njit_inline
def _plane_corners(lower: Any, weights: Any, sizes: Any, a: int, b: int, n: int) -> tuple:
    """Point ``n``'s four corners on a plane whose grid axes read the columns ``a`` and
    ``b`` of ``lower, weights`` (``sizes``: each column's vertex count): the row of the
    lower corner in the plane's channel-last rows, the row stride, the weights
    ``w_00, w_01, w_10, w_11`` (as :mod:`baselines.interp` multiplies them) and whether
    each of the lower and upper vertex along either axis lies inside."""
    i, j, ra, rb = lower[n, a], lower[n, b], sizes[a], sizes[b]
    u0, v0, u1, v1 = weights[n, a, 0], weights[n, a, 1], weights[n, b, 0], weights[n, b, 1]
    return (i * rb + j, rb, u0 * u1, u0 * v1, v0 * u1, v0 * v1, 0 <= i < ra,
            0 <= i + 1 < ra, 0 <= j < rb, 0 <= j + 1 < rb)


@njit_inline
def _plane_sample(T: Any, lower: Any, weights: Any, sizes: Any, a: int, b: int, n: int,
                  s: Any, k: int) -> None:
    """``s[k] [C]``: the plane ``T [R_a·R_b, C]`` at point ``n`` (:func:`_plane_corners`),
    summed corner by corner from a fill of 0 (NaN for a non-finite coordinate)."""
    r, rb, w00, w01, w10, w11, i0, i1, j0, j1 = _plane_corners(lower, weights, sizes, a, b,
                                                               n)
    if i0 and i1 and j0 and j1:                  # the common case, without branches
        for c in range(T.shape[1]):
            s[k, c] = ((w00 * T[r, c] + w01 * T[r + 1, c]) + w10 * T[r + rb, c]) \
                + w11 * T[r + rb + 1, c]
        return
    fill = w00 - w00                             # 0, or NaN where a weight is NaN
    for c in range(T.shape[1]):
        x = fill
        if i0 and j0:
            x += w00 * T[r, c]
        if i0 and j1:
            x += w01 * T[r + 1, c]
        if i1 and j0:
            x += w10 * T[r + rb, c]
        if i1 and j1:
            x += w11 * T[r + rb + 1, c]
        s[k, c] = x


@njit_inline
def _plane_scatter(G: Any, lower: Any, weights: Any, sizes: Any, a: int, b: int, n: int,
                   part: Any, k: int) -> None:
    """``G[corner] += w_corner · part[k]`` over point ``n``'s corners inside the plane,
    in :mod:`baselines.interp`'s corner order."""
    r, rb, w00, w01, w10, w11, i0, i1, j0, j1 = _plane_corners(lower, weights, sizes, a, b,
                                                               n)
    axpy(G, r, w00, part, k, i0 and j0)
    axpy(G, r + 1, w01, part, k, i0 and j1)
    axpy(G, r + rb, w10, part, k, i1 and j0)
    axpy(G, r + rb + 1, w11, part, k, i1 and j1)


@njit_inline
def _line_at(T: Any, lower: Any, weights: Any, sizes: Any, a: int, n: int, s: Any,
             k: int) -> None:
    """``s[k] [C]``: the line ``T`` at point ``n``, its axis read from column ``a``."""
    i, j, u, v, in_i, in_j = line_vertices(lower, weights, sizes, n, a)
    line_sample(T, i, j, u, v, in_i, in_j, s, k)


@njit_inline
def _samples(planes: Any, lines: Any, pcol: Any, lcol: Any, psz: Any, lsz: Any, lo_p: Any,
             w_p: Any, lo_l: Any, w_l: Any, n: int, s: Any) -> None:
    """Point ``n``'s nine samples into ``s [9, C]``: the planes ``P_0..P_2, Q_0..Q_2``
    (rows 0-5; plane ``m`` reads the columns ``pcol[m]`` of ``lo_p, w_p``), then the
    lines ``V_0..V_2`` (rows 6-8; column ``lcol[m]`` of ``lo_l, w_l``). Spelled out, so
    that each factor is read at a constant index of its tuple."""
    _plane_sample(planes[0], lo_p, w_p, psz, pcol[0, 0], pcol[0, 1], n, s, 0)
    _plane_sample(planes[1], lo_p, w_p, psz, pcol[1, 0], pcol[1, 1], n, s, 1)
    _plane_sample(planes[2], lo_p, w_p, psz, pcol[2, 0], pcol[2, 1], n, s, 2)
    _plane_sample(planes[3], lo_p, w_p, psz, pcol[3, 0], pcol[3, 1], n, s, 3)
    _plane_sample(planes[4], lo_p, w_p, psz, pcol[4, 0], pcol[4, 1], n, s, 4)
    _plane_sample(planes[5], lo_p, w_p, psz, pcol[5, 0], pcol[5, 1], n, s, 5)
    _line_at(lines[0], lo_l, w_l, lsz, lcol[0], n, s, 6)
    _line_at(lines[1], lo_l, w_l, lsz, lcol[1], n, s, 7)
    _line_at(lines[2], lo_l, w_l, lsz, lcol[2], n, s, 8)


@njit_borrowing
def _forward(planes: Any, lines: Any, pcol: Any, lcol: Any, psz: Any, lsz: Any, lo_p: Any,
             w_p: Any, lo_l: Any, w_l: Any, rank: int, out: Any, s: Any, acc: Any) -> None:
    """``out [N, F]``: the rank sums of the three products (module docstring); ``s [9, C]``
    and ``acc [C]`` scratch."""
    c_all = planes[0].shape[1]
    for n in range(lo_p.shape[0]):
        _samples(planes, lines, pcol, lcol, psz, lsz, lo_p, w_p, lo_l, w_l, n, s)
        for c in range(c_all):
            acc[c] = ((s[0, c] * s[3, c]) * s[6, c] + (s[1, c] * s[4, c]) * s[7, c]) \
                + (s[2, c] * s[5, c]) * s[8, c]
        rank_sums(acc, rank, c_all, out, n)


@njit_inline
def _term_gradients(k: int, s: Any, g: Any, buf: Any, b: int, c_all: int) -> None:
    """Term ``k``'s sample gradients, ``(P_k · Q_k) · V_k`` in autograd's order, into
    ``buf[b, k]`` (``P_k``), ``buf[b, 3 + k]`` (``Q_k``), ``buf[b, 6 + k]`` (``V_k``);
    ``g [C]``: ``∂L/∂o`` per channel. ``buf[b, 6 + k]`` first holds ``g V_k``."""
    gv = buf[b, 6 + k]
    for c in range(c_all):
        gv[c] = g[c] * s[6 + k, c]
    for c in range(c_all):
        buf[b, k, c] = gv[c] * s[3 + k, c]
    for c in range(c_all):
        buf[b, 3 + k, c] = gv[c] * s[k, c]
    for c in range(c_all):
        gv[c] = g[c] * (s[k, c] * s[3 + k, c])


@njit_borrowing
def _backward(planes: Any, lines: Any, pcol: Any, lcol: Any, psz: Any, lsz: Any, lo_p: Any,
              w_p: Any, lo_l: Any, w_l: Any, feature: Any, grad: Any, GP: Any, GL: Any,
              s: Any, buf: Any) -> None:
    """``GP[m] += ∂L/∂(plane m)``, ``GL[m] += ∂L/∂V_m`` for ``grad = ∂L/∂out [N, F]``
    (module docstring); ``feature [C]``: each channel's feature ``f(c)``; ``s [9, C]``
    and ``buf [B, 10, C]`` scratch.

    In blocks of ``B`` points: each point's nine sample gradients into ``buf``, then
    factor by factor the block's scatter, so that one gradient table at a time is
    written (the nine with the factors are ~2.7 MB at the CPU size, more than a core's
    L2 cache). Each table still takes its points in order and their corners in order,
    as :mod:`baselines.interp`'s scatter. Each row of ``buf`` is written by a loop over
    all ``C`` channels that writes nothing else, which LLVM vectorises."""
    c_all, B, N = planes[0].shape[1], buf.shape[0], lo_p.shape[0]
    for a in range(0, N, B):
        e = min(a + B, N)
        for b in range(e - a):
            n = a + b
            _samples(planes, lines, pcol, lcol, psz, lsz, lo_p, w_p, lo_l, w_l, n, s)
            g, row = buf[b, 9], grad[n]
            for c in range(c_all):
                g[c] = row[feature[c]]
            _term_gradients(0, s, g, buf, b, c_all)
            _term_gradients(1, s, g, buf, b, c_all)
            _term_gradients(2, s, g, buf, b, c_all)
        _scatter_block(GP[0], lo_p, w_p, psz, pcol[0, 0], pcol[0, 1], a, e, buf, 0)
        _scatter_block(GP[1], lo_p, w_p, psz, pcol[1, 0], pcol[1, 1], a, e, buf, 1)
        _scatter_block(GP[2], lo_p, w_p, psz, pcol[2, 0], pcol[2, 1], a, e, buf, 2)
        _scatter_block(GP[3], lo_p, w_p, psz, pcol[3, 0], pcol[3, 1], a, e, buf, 3)
        _scatter_block(GP[4], lo_p, w_p, psz, pcol[4, 0], pcol[4, 1], a, e, buf, 4)
        _scatter_block(GP[5], lo_p, w_p, psz, pcol[5, 0], pcol[5, 1], a, e, buf, 5)
        _scatter_line_block(GL[0], lo_l, w_l, lsz, lcol[0], a, e, buf, 6)
        _scatter_line_block(GL[1], lo_l, w_l, lsz, lcol[1], a, e, buf, 7)
        _scatter_line_block(GL[2], lo_l, w_l, lsz, lcol[2], a, e, buf, 8)


@njit_inline
def _scatter_block(G: Any, lower: Any, weights: Any, sizes: Any, pa: int, pb: int, a: int,
                   e: int, buf: Any, m: int) -> None:
    """The plane gradients ``buf[n − a, m]`` of the points ``a ≤ n < e`` scattered into
    ``G`` (:func:`_plane_scatter`), point by point."""
    for n in range(a, e):
        _plane_scatter(G, lower, weights, sizes, pa, pb, n, buf[n - a], m)


@njit_inline
def _scatter_line_block(G: Any, lower: Any, weights: Any, sizes: Any, col: int, a: int,
                        e: int, buf: Any, m: int) -> None:
    """The line gradients ``buf[n − a, m]`` of the points ``a ≤ n < e`` scattered into
    ``G`` at their two vertices."""
    for n in range(a, e):
        i, j, u, v, in_i, in_j = line_vertices(lower, weights, sizes, n, col)
        axpy(G, i, u, buf[n - a], m, in_i)
        axpy(G, j, v, buf[n - a], m, in_j)


@njit_parallel
def _forward_parts(planes: Any, lines: Any, pcol: Any, lcol: Any, psz: Any, lsz: Any,
                   lo_p: Any, w_p: Any, lo_l: Any, w_l: Any, rank: int, out: Any, s: Any,
                   acc: Any) -> None:
    """:func:`_forward` on ``P`` equal ranges of the points at once, ``s [P, 9, C]`` and
    ``acc [P, C]`` each range's scratch (the same values)."""
    n, p = lo_p.shape[0], s.shape[0]
    for k in prange(p):
        a, b = n * k // p, n * (k + 1) // p
        _forward(planes, lines, pcol, lcol, psz, lsz, lo_p[a:b], w_p[a:b], lo_l[a:b],
                 w_l[a:b], rank, out[a:b], s[k], acc[k])


@njit_parallel
def _backward_parts(planes: Any, lines: Any, pcol: Any, lcol: Any, psz: Any, lsz: Any,
                    lo_p: Any, w_p: Any, lo_l: Any, w_l: Any, feature: Any, grad: Any,
                    GP: Any, GL: Any, s: Any, buf: Any) -> None:
    """:func:`_backward` on ``P`` equal ranges of the points at once, range ``k`` into its
    own copies ``GP[m][k]``, ``GL[m][k]`` (their sum over ``k`` is the gradient) with
    scratch ``s[k] [9, C]``, ``buf[k] [B, 10, C]``."""
    n, p = lo_p.shape[0], s.shape[0]
    for k in prange(p):
        a, b = n * k // p, n * (k + 1) // p
        gp = (GP[0][k], GP[1][k], GP[2][k], GP[3][k], GP[4][k], GP[5][k])
        gl = (GL[0][k], GL[1][k], GL[2][k])
        _backward(planes, lines, pcol, lcol, psz, lsz, lo_p[a:b], w_p[a:b], lo_l[a:b],
                  w_l[a:b], feature, grad[a:b], gp, gl, s[k], buf[k])


class _Corners:
    """The points' corners on the nine factors: one :func:`vertex_corners` pass per
    sampling convention over the distinct (coordinate axis, vertex count) pairs the
    planes, then the lines, read; ``pcol [6, 2]`` / ``lcol [3]`` name each factor's
    columns and ``psz`` / ``lsz`` each column's vertex count."""

    def __init__(self, factors: Sequence[Tensor], axes: Sequence[Sequence[int]],
                 coords: Tensor, align: Sequence[bool], padding: str):
        self.pcol, self.psz, self.lo_p, self.w_p = self._group(
            factors[:6], axes[:6], coords, align[0], padding)
        lcol, self.lsz, self.lo_l, self.w_l = self._group(
            factors[6:], axes[6:], coords, align[6], padding)
        self.lcol = np.ascontiguousarray(lcol[:, 0])

    @staticmethod
    def _group(factors: Sequence[Tensor], axes: Sequence[Sequence[int]], coords: Tensor,
               align: bool, padding: str) -> tuple:
        """``(cols [M, d], sizes [K], lower [N, K], weights [N, K, 2])`` for ``M`` factors
        of ``d`` grid axes read with one convention: the ``K`` distinct (coordinate axis,
        vertex count) pairs they read, each a column of ``lower`` (int64) and ``weights``,
        and which column each factor's grid axis reads."""
        keys: list[tuple[int, int]] = []
        cols = []
        for f, ax in zip(factors, axes):
            row = []
            for a, size in zip(ax, f.shape[1:]):
                if (a, size) not in keys:
                    keys.append((int(a), int(size)))
                row.append(keys.index((a, size)))
            cols.append(row)
        sizes = tuple(size for _, size in keys)
        lower, weights = vertex_corners(coords, sizes, align, padding, [a for a, _ in keys])
        return (np.array(cols, dtype=np.int64), np.array(sizes, dtype=np.int64),
                lower.numpy(), weights.numpy())

    def args(self) -> tuple:
        """The kernels' corner arguments, in their order."""
        return (self.pcol, self.lcol, self.psz, self.lsz, self.lo_p, self.w_p, self.lo_l,
                self.w_l)


def _tables(factors: Sequence[Tensor]) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
    """The planes' and the lines' channel-last rows (``[Π R, C]``)."""
    rows = [channel_rows(f).numpy() for f in factors]
    return tuple(rows[:6]), tuple(rows[6:])


class _HexRankSum(torch.autograd.Function):
    """``(corners, rank, *nine factors) -> [N, F]``; gradients reach the factors only."""

    @staticmethod
    def forward(ctx: Any, corners: _Corners, rank: int, *factors: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(*factors)
        ctx.corners, ctx.rank = corners, rank
        return _read(factors, corners, rank)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        factors, corners = ctx.saved_tensors, ctx.corners
        planes, lines = _tables(factors)
        n = corners.lo_p.shape[0]
        # [P, rows, C] each; a point writes 4 rows of each plane and 2 of each line
        sums = scatter_copies(n, [*planes, *lines], factors[0].dtype, corners=6 * 4 + 3 * 2)
        p, c, dtype = sums[0].shape[0], planes[0].shape[1], planes[0].dtype
        feature = np.arange(c, dtype=np.int64) // ctx.rank
        args = (planes, lines, *corners.args(), feature, grad.contiguous().numpy())
        if p == 1:
            _backward(*args, tuple(s[0].numpy() for s in sums[:6]),
                      tuple(s[0].numpy() for s in sums[6:]), np.empty((9, c), dtype),
                      np.empty((BLOCK, 10, c), dtype))
            tables = [s[0] for s in sums]
        else:
            _backward_parts(*args, tuple(s.numpy() for s in sums[:6]),
                            tuple(s.numpy() for s in sums[6:]),
                            np.empty((p, 9, c + PAD), dtype),
                            np.empty((p, BLOCK, 10, c + PAD), dtype))
            tables = [s.sum(0) for s in sums]
        grads = [t.reshape(*f.shape[1:], c).movedim(-1, 0) for t, f in zip(tables, factors)]
        return (None, None, *grads)


def _read(factors: Sequence[Tensor], corners: _Corners, rank: int) -> Tensor:
    """The forward pass: ``[N, F]``."""
    planes, lines = _tables(factors)
    c = planes[0].shape[1]
    n = corners.lo_p.shape[0]
    out = factors[0].new_empty(n, c // rank)
    args = (planes, lines, *corners.args(), rank, out.numpy())
    run_forward(_forward, _forward_parts, args, n, 9, c, out.numpy().dtype)
    return out


def supported(factors: Sequence[Tensor], axes: Sequence[Sequence[int]], coords: Tensor,
              align_corners: Sequence[bool]) -> bool:
    """Whether :func:`hex_rank_sum` serves this call: six planes ``[C, R_a, R_b]`` of one
    sampling convention, then three lines ``[C, R]`` of one (``axes``: one coordinate
    column per grid axis of each), at most :data:`MAX_BYTES` in all, and the conditions of
    :func:`~baselines.fused_kernels.supported_factors`."""
    return (len(factors) == 9 and all(f.dim() == 3 for f in factors[:6])
            and all(f.dim() == 2 for f in factors[6:]) and len(align_corners) == 9
            and len(axes) == 9 and all(len(a) == f.dim() - 1 for a, f in zip(axes, factors))
            and all(0 <= c < 4 for a in axes for c in a)
            and len(set(align_corners[:6])) == 1 and len(set(align_corners[6:])) == 1
            and sum(f.numel() * f.element_size() for f in factors) <= MAX_BYTES
            and supported_factors(list(factors), coords))


def hex_rank_sum(factors: Sequence[Tensor], axes: Sequence[Sequence[int]], coords: Tensor,
                 align_corners: Sequence[bool], padding: str, rank: int) -> Tensor | None:
    """``o [N, F]`` (module docstring) of the factors ``P_0..P_2, Q_0..Q_2, V_0..V_2`` at
    ``coords [N, 4]`` (``[-1, 1]``; factor ``m``'s grid axis ``d`` reads the column
    ``axes[m][d]``), differentiable with respect to the factors; ``None`` where
    :func:`supported` is false.

    Raises:
        InputError: ``rank`` does not divide the factors' channels.
    """
    if not supported(factors, axes, coords, align_corners):
        return None
    if rank < 1 or factors[0].shape[0] % rank:
        raise InputError("baselines.hex_fused", "rank",
                         f"a divisor of the factors' {factors[0].shape[0]} channels", rank)
    corners = _Corners(factors, axes, coords, align_corners, padding)
    if torch.is_grad_enabled() and any(f.requires_grad for f in factors):
        return _HexRankSum.apply(corners, int(rank), *factors)
    return _read(factors, corners, int(rank))
