"""The factorised backbones' rank sums fused on the CPU, with their gradients:
TensoRF-CP's four line products (:func:`cp_rank_sum`) and HexPlane's three
plane · plane · line products (:func:`hex_rank_sum`).

The PyTorch reference of both is :meth:`baselines.factorised.FactorisedField.rank_sum`:
sample every factor with ``grid_sample``, combine the samples channel by channel, sum
over the rank. A factor ``[C, R_0, …]`` (``C = F·R`` channels, stored channel-last on a
CPU, :func:`baselines.grids.device_layout`) is read here as rows ``[Π R, C]``
(:func:`channel_rows`) at a point's lower vertex ``i_k = ⌊p_k⌋`` and weights
``(u_k, v_k) = (1 − (p_k − i_k), p_k − i_k)`` per axis, ``p_k`` the coordinate in vertex
units (:func:`vertex_corners`: ``grid_sample``'s ``(c + 1)/2 · (R − 1)`` with
``align_corners``, ``((c + 1) R − 1)/2`` without, clamped to ``[0, R − 1]`` with border
padding). A corner outside the factor is not read (zero padding). A line's sample is
``s[c] = u T[i, c] + v T[i + 1, c]``, a plane's the four corners' weighted sum.

TensoRF-CP, lines ``T_a`` (``a = x, y, z, t``):

.. math::
    o_f = \\sum_{r=0}^{R-1} ((s_x s_y) s_z) s_t\\,[fR + r],\\qquad
    \\frac{\\partial L}{\\partial T_a[i_a + b, c]} \\mathrel{+}= w_{a,b}\\,
    \\frac{\\partial L}{\\partial o_{f(c)}} \\prod_{a' \\ne a} s_{a'}[c].

HexPlane, spatial planes ``P_k``, space-time planes ``Q_k``, lines ``V_k``:

.. math::
    o_f = \\sum_{r=0}^{R-1} \\Big(\\big((P_0 Q_0) V_0 + (P_1 Q_1) V_1\\big)
          + (P_2 Q_2) V_2\\Big)[fR + r],

with the gradient of each sample, in autograd's order for ``(P_k · Q_k) · V_k``,
``∂L/∂V_k = g (P_k Q_k)``, ``∂L/∂P_k = (g V_k) Q_k``, ``∂L/∂Q_k = (g V_k) P_k``
(``g[c] = ∂L/∂o_{f(c)}``), scattered over the factor's corners.

Why: factor by factor, the samples, the products and their gradients are ``[N, C]``
tensors that stream through memory. Here one compiled loop per pass reads the small
factors (in cache) and writes ``[N, F]``; the samples are recomputed in the backward
pass. HexPlane's factors must stay near the core, as every point reads all nine:
:data:`MAX_BYTES`. With two or more torch threads the points are split into ranges run
on numba's threads (:func:`~eventrecon.kernels.jit.parts`), each range scattering into
its own copy of the factors' gradients, summed at the end (so split between threads the
gradient is the sum of each range's one-thread gradient, to the bit).

Each sample is summed from a fill of 0 (NaN where a weight is NaN: a non-finite
coordinate reads NaN, as ``grid_sample`` with zero padding) plus each corner inside in
corner order, and the products in the reference's order; the values and gradients agree
with the reference's to rounding (``grid_sample`` rounds its weights and accumulates its
gradient in other orders), and the forward's rank sum runs in another order than
``Tensor.sum``. The backward reads the factors again, so a factor changed in place
between the passes raises autograd's version error. :func:`cp_unsupported` and
:func:`hex_unsupported` say where a kernel does not apply (no numba, a GPU, coordinates
that need a gradient, other shapes or dtypes, factors too large to stay in cache).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from eventrecon.common.errors import InputError
from eventrecon.kernels.jit import AVAILABLE, GRAIN, inline, parallel, parts, prange, serial

__all__ = ["BLOCK", "MAX_BYTES", "PAD", "channel_rows", "cp_rank_sum", "cp_unsupported",
           "hex_rank_sum", "hex_unsupported", "vertex_corners"]

#: Unused channels at the end of each range's scratch rows, so that two threads never
#: write one cache line (64 bytes, 16 float32).
PAD = 16
#: Points per block of HexPlane's backward pass (:func:`_hex_backward`).
BLOCK = 64
#: HexPlane's kernel serves factors of at most this many bytes in all (as read: the
#: density's leading channels alone count a quarter): every point reads all nine, so
#: they must stay in a core's cache (the CPU size, 48 vertices per axis and 32 channels,
#: is 1.4 MB; the authors' 500² planes are not served).
MAX_BYTES = 6 << 20


# ---------------------------------------------------------------- corners and weights
@serial
def _vertex_corners(coords: Any, axes: Any, sizes: Any, align: bool, border: bool,
                    units: Any, lower: Any, weights: Any) -> None:
    """Per point and column ``axes[k]`` of ``coords``: ``p`` in vertex units, its lower
    vertex ``⌊p⌋`` (−2 for a non-finite or very negative one, 2³¹ for a huge one: outside
    every factor) and weights ``(1 − (p − ⌊p⌋), p − ⌊p⌋)``, with the expressions in the
    coordinates' dtype (``sizes``: the vertex counts, and ``units``: 1, 2 and 2³¹, both in
    that dtype)."""
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


@parallel
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
    """Normalised CPU coordinates (float32/float64) → the lower vertex ``[N, d]`` (int64)
    and the weights ``[N, d, 2]`` (their dtype) of the ``d`` columns ``axes`` (all of
    ``coords [N, d]`` when ``None``) on axes of ``sizes`` vertices (:func:`_vertex_corners`).

    Raises:
        InputError: ``sizes`` and the columns read differ in number, or a column is
            outside ``coords``.
    """
    cols = list(range(coords.shape[1])) if axes is None else [int(a) for a in axes]
    if len(sizes) != len(cols) or not all(0 <= a < coords.shape[1] for a in cols):
        raise InputError("eventrecon.kernels.factor_grids", "axes/sizes",
                         f"one size per column read, columns of [N, {coords.shape[1]}]",
                         f"axes {cols}, sizes {list(sizes)}")
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


def channel_rows(grid: Tensor) -> Tensor:
    """``grid [C, *R]`` → ``[Π R, C]``, channel-last rows (a view when the grid is stored
    channel-last, :func:`baselines.grids.channels_last`)."""
    return grid.detach().movedim(0, -1).reshape(-1, grid.shape[0]).contiguous()


# ---------------------------------------------------------------- shared per-point pieces
@inline
def _line_vertices(lower: Any, weights: Any, sizes: Any, n: int, a: int
                   ) -> tuple[int, int, Any, Any, bool, bool]:
    """Point ``n``'s two vertices along column ``a`` of ``lower, weights`` (a line of
    ``sizes[a]`` vertices): their rows, weights and whether each lies inside."""
    i = lower[n, a]
    return (i, i + 1, weights[n, a, 0], weights[n, a, 1], 0 <= i < sizes[a],
            0 <= i + 1 < sizes[a])


@inline
def _line_sample(T: Any, i: int, j: int, u: Any, v: Any, in_i: bool, in_j: bool, s: Any,
                 k: int) -> None:
    """``s[k] [C]``: the line ``T [R, C]`` at vertices ``i, j`` with weights ``u, v``."""
    if in_i and in_j:                            # the common case, without branches
        for c in range(T.shape[1]):
            s[k, c] = u * T[i, c] + v * T[j, c]
        return
    fill = u if u != u else u - u                # u − u: a zero of the weights' dtype
    for c in range(T.shape[1]):
        x = fill
        if in_i:
            x += u * T[i, c]
        if in_j:
            x += v * T[j, c]
        s[k, c] = x


@inline
def _axpy(G: Any, row: int, w: Any, x: Any, a: int, inside: bool) -> None:
    """``G[row] += w · x[a]`` over the channels, for a vertex inside the factor."""
    if inside:
        for c in range(G.shape[1]):
            G[row, c] += w * x[a, c]


@inline
def _rank_sums(prod: Any, rank: int, c_all: int, out: Any, n: int) -> None:
    """``out[n, f] = Σ_r prod[f·R + r]``, each sum from ``r = 0`` up. With four features
    (the full field) the four sums run side by side, the same order, so that one sum's
    additions do not each wait for the one before."""
    if c_all == 4 * rank:
        a0, a1, a2, a3 = prod[0], prod[rank], prod[2 * rank], prod[3 * rank]
        for r in range(1, rank):
            a0 += prod[r]
            a1 += prod[rank + r]
            a2 += prod[2 * rank + r]
            a3 += prod[3 * rank + r]
        out[n, 0], out[n, 1], out[n, 2], out[n, 3] = a0, a1, a2, a3
        return
    for f in range(c_all // rank):
        acc = prod[f * rank]
        for r in range(1, rank):
            acc += prod[f * rank + r]
        out[n, f] = acc


def _run_forward(kernel: Any, kernel_parts: Any, args: tuple, n_points: int,
                 n_factors: int, channels: int, dtype: Any) -> None:
    """A fused forward pass over ``n_points``: ``kernel(*args, s, acc)`` with scratch
    ``s [n_factors, C]`` and ``acc [C]``, or, where the points split into ``P > 1``
    ranges, ``kernel_parts`` with each range's scratch padded apart (:data:`PAD`)."""
    p = parts(n_points)
    if p == 1:
        kernel(*args, np.empty((n_factors, channels), dtype), np.empty(channels, dtype))
    else:
        kernel_parts(*args, np.empty((p, n_factors, channels + PAD), dtype),
                     np.empty((p, channels + PAD), dtype))


def _scatter_copies(n_points: int, tables: list[np.ndarray], dtype: torch.dtype,
                    corners: int) -> list[Tensor]:
    """Zeroed gradients ``[P, rows, C]`` for each table, one copy per range of the points
    that the backward pass runs on its own thread (``corners``: the rows each point
    scatters into, over all tables): ``P`` ranges while each range's row writes (its
    points times ``corners``) are at least its copies' rows, and it has at least
    :data:`~eventrecon.kernels.jit.GRAIN` points."""
    rows = sum(t.shape[0] for t in tables)
    p = parts(n_points, grain=max(GRAIN, rows // max(corners, 1)))
    return [torch.zeros((p, *t.shape), dtype=dtype) for t in tables]


def _factors_unsupported(factors: Sequence[Tensor], coords: Tensor) -> str | None:
    """The conditions both kernels share (:func:`cp_unsupported`)."""
    if not AVAILABLE:
        return "numba installed"
    if coords.device.type != "cpu" or any(f.device.type != "cpu" for f in factors):
        return "tensors on the CPU"
    if coords.dim() != 2 or coords.shape[1] != 4:
        return "coordinates [N, 4]"
    if coords.dtype not in (torch.float32, torch.float64) or any(
            f.dtype != coords.dtype for f in factors):
        return "factors and coordinates of one dtype, float32 or float64"
    if len({f.shape[0] for f in factors}) != 1:
        return "factors of one channel count"
    if coords.requires_grad and torch.is_grad_enabled():
        return "no gradient with respect to the coordinates"
    return None


def _check_rank(factors: Sequence[Tensor], rank: int) -> None:
    """Raise an :class:`InputError` unless ``rank`` divides the factors' channels."""
    if rank < 1 or factors[0].shape[0] % rank:
        raise InputError("eventrecon.kernels.factor_grids", "rank",
                         f"a divisor of the factors' {factors[0].shape[0]} channels", rank)


def _check(reason: str | None) -> None:
    """Raise an :class:`InputError` naming what a kernel needs and a call lacks."""
    if reason is not None:
        raise InputError("eventrecon.kernels.factor_grids", "factors", reason)


# ---------------------------------------------------------------- TensoRF-CP
@inline
def _cp_samples(T0: Any, T1: Any, T2: Any, T3: Any, sizes: Any, lower: Any, weights: Any,
                n: int, s: Any) -> tuple:
    """Point ``n``'s four line samples into ``s [4, C]``; returns each line's vertices
    (rows, weights, inside) for the scatter."""
    a0, b0, u0, v0, in_a0, in_b0 = _line_vertices(lower, weights, sizes, n, 0)
    a1, b1, u1, v1, in_a1, in_b1 = _line_vertices(lower, weights, sizes, n, 1)
    a2, b2, u2, v2, in_a2, in_b2 = _line_vertices(lower, weights, sizes, n, 2)
    a3, b3, u3, v3, in_a3, in_b3 = _line_vertices(lower, weights, sizes, n, 3)
    _line_sample(T0, a0, b0, u0, v0, in_a0, in_b0, s, 0)
    _line_sample(T1, a1, b1, u1, v1, in_a1, in_b1, s, 1)
    _line_sample(T2, a2, b2, u2, v2, in_a2, in_b2, s, 2)
    _line_sample(T3, a3, b3, u3, v3, in_a3, in_b3, s, 3)
    return ((a0, b0, u0, v0, in_a0, in_b0), (a1, b1, u1, v1, in_a1, in_b1),
            (a2, b2, u2, v2, in_a2, in_b2), (a3, b3, u3, v3, in_a3, in_b3))


@serial
def _cp_forward(T0: Any, T1: Any, T2: Any, T3: Any, sizes: Any, lower: Any, weights: Any,
                rank: int, out: Any, s: Any, prod: Any) -> None:
    """``out [N, F]``: the rank sums of the line products (module docstring);
    ``s [4, C]`` and ``prod [C]`` scratch."""
    c_all = T0.shape[1]
    for n in range(lower.shape[0]):
        _cp_samples(T0, T1, T2, T3, sizes, lower, weights, n, s)
        for c in range(c_all):
            prod[c] = ((s[0, c] * s[1, c]) * s[2, c]) * s[3, c]
        _rank_sums(prod, rank, c_all, out, n)


@serial
def _cp_backward(T0: Any, T1: Any, T2: Any, T3: Any, sizes: Any, lower: Any, weights: Any,
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
        p0, p1, p2, p3 = _cp_samples(T0, T1, T2, T3, sizes, lower, weights, n, s)
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
            _axpy(G, p[0], p[2], part, k, p[4])
            _axpy(G, p[1], p[3], part, k, p[5])


@parallel
def _cp_forward_parts(T0: Any, T1: Any, T2: Any, T3: Any, sizes: Any, lower: Any,
                      weights: Any, rank: int, out: Any, s: Any, prod: Any) -> None:
    """:func:`_cp_forward` on ``P`` equal ranges of the points at once, ``s [P, 4, C]``
    and ``prod [P, C]`` each range's scratch (the same values)."""
    n, p = lower.shape[0], s.shape[0]
    for k in prange(p):
        a, b = n * k // p, n * (k + 1) // p
        _cp_forward(T0, T1, T2, T3, sizes, lower[a:b], weights[a:b], rank, out[a:b], s[k],
                    prod[k])


@parallel
def _cp_backward_parts(T0: Any, T1: Any, T2: Any, T3: Any, sizes: Any, lower: Any,
                       weights: Any, feature: Any, grad: Any, G0: Any, G1: Any, G2: Any,
                       G3: Any, s: Any, part: Any) -> None:
    """:func:`_cp_backward` on ``P`` equal ranges of the points at once, range ``k`` into
    its own ``G_a[k]`` (``G_a [P, R_a, C]``; their sum over ``k`` is the gradient) with
    scratch ``s[k] [4, C]``, ``part[k] [5, C]``."""
    n, p = lower.shape[0], s.shape[0]
    for k in prange(p):
        a, b = n * k // p, n * (k + 1) // p
        _cp_backward(T0, T1, T2, T3, sizes, lower[a:b], weights[a:b], feature, grad[a:b],
                     G0[k], G1[k], G2[k], G3[k], s[k], part[k])


def _line_sizes(lines: Sequence[Tensor]) -> np.ndarray:
    """``[4]`` int64: each line's vertex count."""
    return np.array([line.shape[1] for line in lines], dtype=np.int64)


def _cp_read(lines: Sequence[Tensor], lower: Tensor, weights: Tensor, rank: int) -> Tensor:
    """TensoRF-CP's forward pass: ``[N, F]``."""
    c = lines[0].shape[0]
    out = lines[0].new_empty(lower.shape[0], c // rank)
    args = (*(channel_rows(line).numpy() for line in lines), _line_sizes(lines),
            lower.numpy(), weights.numpy(), rank, out.numpy())
    _run_forward(_cp_forward, _cp_forward_parts, args, lower.shape[0], 4, c,
                 out.numpy().dtype)
    return out


class _CPRankSum(torch.autograd.Function):
    """``(T_x, T_y, T_z, T_t [C, R_a], lower, weights, rank) -> [N, F]``; gradients reach
    the lines only."""

    @staticmethod
    def forward(ctx: Any, l0: Tensor, l1: Tensor, l2: Tensor, l3: Tensor, lower: Tensor,  # type: ignore[override]
                weights: Tensor, rank: int) -> Tensor:
        lines = (l0, l1, l2, l3)
        ctx.save_for_backward(*lines, lower, weights)
        ctx.rank = rank
        return _cp_read(lines, lower, weights, rank)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        *lines, lower, weights = ctx.saved_tensors
        tables = [channel_rows(line).numpy() for line in lines]
        # [P, R_a, C] each; a point writes 2 rows of each of the 4 lines
        sums = _scatter_copies(lower.shape[0], tables, lines[0].dtype, corners=4 * 2)
        p = sums[0].shape[0]
        c, dtype = tables[0].shape[1], tables[0].dtype
        samples = np.empty((p, 4, c + PAD), dtype)
        part = np.empty((p, 5, c + PAD), dtype)
        feature = np.arange(c, dtype=np.int64) // ctx.rank
        args = (*tables, _line_sizes(lines), lower.numpy(), weights.numpy(), feature,
                grad.contiguous().numpy())
        if p == 1:
            _cp_backward(*args, *(s[0].numpy() for s in sums), samples[0], part[0])
            return (*(s[0].t() for s in sums), None, None, None)
        _cp_backward_parts(*args, *(s.numpy() for s in sums), samples, part)
        return (*(s.sum(0).t() for s in sums), None, None, None)


def cp_unsupported(lines: Sequence[Tensor], coords: Tensor,
                   align_corners: Sequence[bool]) -> str | None:
    """What :func:`cp_rank_sum` needs and this call lacks, or ``None`` where it applies:
    numba, four lines ``[C, R_a]`` of one ``C`` and one float32/float64 dtype on the CPU,
    one sampling convention, coordinates ``[N, 4]`` of that dtype that need no gradient.

    >>> cp_unsupported([torch.zeros(4, 5)] * 3, torch.zeros(2, 4), [False] * 3)
    'four lines [C, R]'
    """
    if len(lines) != 4 or any(line.dim() != 2 for line in lines):
        return "four lines [C, R]"
    if len(set(align_corners)) != 1:
        return "lines of one sampling convention"
    return _factors_unsupported(lines, coords)


def cp_rank_sum(lines: Sequence[Tensor], coords: Tensor, align_corners: Sequence[bool],
                padding: str, rank: int) -> Tensor:
    """``o [N, F]`` (module docstring) of the lines ``[C, R_a]`` at ``coords [N, 4]``
    (``[-1, 1]``, the lines' axes in order), differentiable with respect to the lines.

    Raises:
        InputError: :func:`cp_unsupported` names a reason, or ``rank`` does not divide
            the lines' channels.
    """
    _check(cp_unsupported(lines, coords, align_corners))
    _check_rank(lines, rank)
    sizes = tuple(int(line.shape[1]) for line in lines)
    lower, weights = vertex_corners(coords, sizes, align_corners[0], padding)
    if torch.is_grad_enabled() and any(line.requires_grad for line in lines):
        return _CPRankSum.apply(*lines, lower, weights, int(rank))
    return _cp_read(lines, lower, weights, int(rank))


# ---------------------------------------------------------------- HexPlane
@inline
def _plane_corners(lower: Any, weights: Any, sizes: Any, a: int, b: int, n: int) -> tuple:
    """Point ``n``'s four corners on a plane whose grid axes read the columns ``a`` and
    ``b`` of ``lower, weights`` (``sizes``: each column's vertex count): the row of the
    lower corner in the plane's channel-last rows, the row stride, the weights
    ``w_00, w_01, w_10, w_11`` and whether each of the lower and upper vertex along
    either axis lies inside."""
    i, j, ra, rb = lower[n, a], lower[n, b], sizes[a], sizes[b]
    u0, v0, u1, v1 = weights[n, a, 0], weights[n, a, 1], weights[n, b, 0], weights[n, b, 1]
    return (i * rb + j, rb, u0 * u1, u0 * v1, v0 * u1, v0 * v1, 0 <= i < ra,
            0 <= i + 1 < ra, 0 <= j < rb, 0 <= j + 1 < rb)


@inline
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


@inline
def _plane_scatter(G: Any, lower: Any, weights: Any, sizes: Any, a: int, b: int, n: int,
                   part: Any, k: int) -> None:
    """``G[corner] += w_corner · part[k]`` over point ``n``'s corners inside the plane,
    in corner order."""
    r, rb, w00, w01, w10, w11, i0, i1, j0, j1 = _plane_corners(lower, weights, sizes, a, b,
                                                               n)
    _axpy(G, r, w00, part, k, i0 and j0)
    _axpy(G, r + 1, w01, part, k, i0 and j1)
    _axpy(G, r + rb, w10, part, k, i1 and j0)
    _axpy(G, r + rb + 1, w11, part, k, i1 and j1)


@inline
def _line_at(T: Any, lower: Any, weights: Any, sizes: Any, a: int, n: int, s: Any,
             k: int) -> None:
    """``s[k] [C]``: the line ``T`` at point ``n``, its axis read from column ``a``."""
    i, j, u, v, in_i, in_j = _line_vertices(lower, weights, sizes, n, a)
    _line_sample(T, i, j, u, v, in_i, in_j, s, k)


@inline
def _hex_samples(planes: Any, lines: Any, pcol: Any, lcol: Any, psz: Any, lsz: Any,
                 lo_p: Any, w_p: Any, lo_l: Any, w_l: Any, n: int, s: Any) -> None:
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


@serial
def _hex_forward(planes: Any, lines: Any, pcol: Any, lcol: Any, psz: Any, lsz: Any,
                 lo_p: Any, w_p: Any, lo_l: Any, w_l: Any, rank: int, out: Any, s: Any,
                 acc: Any) -> None:
    """``out [N, F]``: the rank sums of the three products (module docstring);
    ``s [9, C]`` and ``acc [C]`` scratch."""
    c_all = planes[0].shape[1]
    for n in range(lo_p.shape[0]):
        _hex_samples(planes, lines, pcol, lcol, psz, lsz, lo_p, w_p, lo_l, w_l, n, s)
        for c in range(c_all):
            acc[c] = ((s[0, c] * s[3, c]) * s[6, c] + (s[1, c] * s[4, c]) * s[7, c]) \
                + (s[2, c] * s[5, c]) * s[8, c]
        _rank_sums(acc, rank, c_all, out, n)


@inline
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


@inline
def _scatter_block(G: Any, lower: Any, weights: Any, sizes: Any, pa: int, pb: int, a: int,
                   e: int, buf: Any, m: int) -> None:
    """The plane gradients ``buf[n − a, m]`` of the points ``a ≤ n < e`` scattered into
    ``G`` (:func:`_plane_scatter`), point by point."""
    for n in range(a, e):
        _plane_scatter(G, lower, weights, sizes, pa, pb, n, buf[n - a], m)


@inline
def _scatter_line_block(G: Any, lower: Any, weights: Any, sizes: Any, col: int, a: int,
                        e: int, buf: Any, m: int) -> None:
    """The line gradients ``buf[n − a, m]`` of the points ``a ≤ n < e`` scattered into
    ``G`` at their two vertices."""
    for n in range(a, e):
        i, j, u, v, in_i, in_j = _line_vertices(lower, weights, sizes, n, col)
        _axpy(G, i, u, buf[n - a], m, in_i)
        _axpy(G, j, v, buf[n - a], m, in_j)


@serial
def _hex_backward(planes: Any, lines: Any, pcol: Any, lcol: Any, psz: Any, lsz: Any,
                  lo_p: Any, w_p: Any, lo_l: Any, w_l: Any, feature: Any, grad: Any,
                  GP: Any, GL: Any, s: Any, buf: Any) -> None:
    """``GP[m] += ∂L/∂(plane m)``, ``GL[m] += ∂L/∂V_m`` for ``grad = ∂L/∂out [N, F]``
    (module docstring); ``feature [C]``: each channel's feature ``f(c)``; ``s [9, C]``
    and ``buf [B, 10, C]`` scratch.

    In blocks of ``B`` points: each point's nine sample gradients into ``buf``, then
    factor by factor the block's scatter, so that one gradient table at a time is
    written (the nine with the factors are ~2.7 MB at the CPU size, more than a core's
    L2 cache). Each table still takes its points in order and their corners in order.
    Each row of ``buf`` is written by a loop over all ``C`` channels that writes nothing
    else, which LLVM vectorises."""
    c_all, B, N = planes[0].shape[1], buf.shape[0], lo_p.shape[0]
    for a in range(0, N, B):
        e = min(a + B, N)
        for b in range(e - a):
            n = a + b
            _hex_samples(planes, lines, pcol, lcol, psz, lsz, lo_p, w_p, lo_l, w_l, n, s)
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


@parallel
def _hex_forward_parts(planes: Any, lines: Any, pcol: Any, lcol: Any, psz: Any, lsz: Any,
                       lo_p: Any, w_p: Any, lo_l: Any, w_l: Any, rank: int, out: Any,
                       s: Any, acc: Any) -> None:
    """:func:`_hex_forward` on ``P`` equal ranges of the points at once, ``s [P, 9, C]``
    and ``acc [P, C]`` each range's scratch (the same values)."""
    n, p = lo_p.shape[0], s.shape[0]
    for k in prange(p):
        a, b = n * k // p, n * (k + 1) // p
        _hex_forward(planes, lines, pcol, lcol, psz, lsz, lo_p[a:b], w_p[a:b], lo_l[a:b],
                     w_l[a:b], rank, out[a:b], s[k], acc[k])


@parallel
def _hex_backward_parts(planes: Any, lines: Any, pcol: Any, lcol: Any, psz: Any, lsz: Any,
                        lo_p: Any, w_p: Any, lo_l: Any, w_l: Any, feature: Any, grad: Any,
                        GP: Any, GL: Any, s: Any, buf: Any) -> None:
    """:func:`_hex_backward` on ``P`` equal ranges of the points at once, range ``k``
    into its own copies ``GP[m][k]``, ``GL[m][k]`` (their sum over ``k`` is the
    gradient) with scratch ``s[k] [9, C]``, ``buf[k] [B, 10, C]``."""
    n, p = lo_p.shape[0], s.shape[0]
    for k in prange(p):
        a, b = n * k // p, n * (k + 1) // p
        gp = (GP[0][k], GP[1][k], GP[2][k], GP[3][k], GP[4][k], GP[5][k])
        gl = (GL[0][k], GL[1][k], GL[2][k])
        _hex_backward(planes, lines, pcol, lcol, psz, lsz, lo_p[a:b], w_p[a:b], lo_l[a:b],
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


def _hex_tables(factors: Sequence[Tensor]
                ) -> tuple[tuple[np.ndarray, ...], tuple[np.ndarray, ...]]:
    """The planes' and the lines' channel-last rows (``[Π R, C]``)."""
    rows = [channel_rows(f).numpy() for f in factors]
    return tuple(rows[:6]), tuple(rows[6:])


def _hex_read(factors: Sequence[Tensor], corners: _Corners, rank: int) -> Tensor:
    """HexPlane's forward pass: ``[N, F]``."""
    planes, lines = _hex_tables(factors)
    c = planes[0].shape[1]
    n = corners.lo_p.shape[0]
    out = factors[0].new_empty(n, c // rank)
    args = (planes, lines, *corners.args(), rank, out.numpy())
    _run_forward(_hex_forward, _hex_forward_parts, args, n, 9, c, out.numpy().dtype)
    return out


class _HexRankSum(torch.autograd.Function):
    """``(corners, rank, *nine factors) -> [N, F]``; gradients reach the factors only."""

    @staticmethod
    def forward(ctx: Any, corners: _Corners, rank: int, *factors: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(*factors)
        ctx.corners, ctx.rank = corners, rank
        return _hex_read(factors, corners, rank)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        factors, corners = ctx.saved_tensors, ctx.corners
        planes, lines = _hex_tables(factors)
        n = corners.lo_p.shape[0]
        # [P, rows, C] each; a point writes 4 rows of each plane and 2 of each line
        sums = _scatter_copies(n, [*planes, *lines], factors[0].dtype, corners=6 * 4 + 3 * 2)
        p, c, dtype = sums[0].shape[0], planes[0].shape[1], planes[0].dtype
        feature = np.arange(c, dtype=np.int64) // ctx.rank
        args = (planes, lines, *corners.args(), feature, grad.contiguous().numpy())
        if p == 1:
            _hex_backward(*args, tuple(s[0].numpy() for s in sums[:6]),
                          tuple(s[0].numpy() for s in sums[6:]), np.empty((9, c), dtype),
                          np.empty((BLOCK, 10, c), dtype))
            tables = [s[0] for s in sums]
        else:
            _hex_backward_parts(*args, tuple(s.numpy() for s in sums[:6]),
                                tuple(s.numpy() for s in sums[6:]),
                                np.empty((p, 9, c + PAD), dtype),
                                np.empty((p, BLOCK, 10, c + PAD), dtype))
            tables = [s.sum(0) for s in sums]
        grads = [t.reshape(*f.shape[1:], c).movedim(-1, 0) for t, f in zip(tables, factors)]
        return (None, None, *grads)


def hex_unsupported(factors: Sequence[Tensor], axes: Sequence[Sequence[int]],
                    coords: Tensor, align_corners: Sequence[bool]) -> str | None:
    """What :func:`hex_rank_sum` needs and this call lacks, or ``None`` where it applies:
    six planes ``[C, R_a, R_b]`` of one sampling convention, then three lines ``[C, R]``
    of one (``axes``: one coordinate column 0..3 per grid axis of each), at most
    :data:`MAX_BYTES` in all, and the conditions :func:`cp_unsupported` names for the
    lines' dtype, device and coordinates.

    >>> hex_unsupported([torch.zeros(4, 600, 600)] * 6 + [torch.zeros(4, 600)] * 3,
    ...                 [(0, 1)] * 6 + [(0,)] * 3, torch.zeros(2, 4), [True] * 6 + [False] * 3)
    'factors of at most 6291456 bytes in all (they must stay in cache)'
    """
    if (len(factors) != 9 or any(f.dim() != 3 for f in factors[:6])
            or any(f.dim() != 2 for f in factors[6:]) or len(align_corners) != 9
            or len(axes) != 9 or any(len(a) != f.dim() - 1 for a, f in zip(axes, factors))
            or not all(0 <= c < 4 for a in axes for c in a)):
        return "six planes then three lines, each axis reading a coordinate column 0..3"
    if len(set(align_corners[:6])) != 1 or len(set(align_corners[6:])) != 1:
        return "planes of one sampling convention and lines of one"
    if sum(f.numel() * f.element_size() for f in factors) > MAX_BYTES:
        return f"factors of at most {MAX_BYTES} bytes in all (they must stay in cache)"
    return _factors_unsupported(factors, coords)


def hex_rank_sum(factors: Sequence[Tensor], axes: Sequence[Sequence[int]], coords: Tensor,
                 align_corners: Sequence[bool], padding: str, rank: int) -> Tensor:
    """``o [N, F]`` (module docstring) of the factors ``P_0..P_2, Q_0..Q_2, V_0..V_2`` at
    ``coords [N, 4]`` (``[-1, 1]``; factor ``m``'s grid axis ``d`` reads the column
    ``axes[m][d]``), differentiable with respect to the factors.

    Raises:
        InputError: :func:`hex_unsupported` names a reason, or ``rank`` does not divide
            the factors' channels.
    """
    _check(hex_unsupported(factors, axes, coords, align_corners))
    _check_rank(factors, rank)
    corners = _Corners(factors, axes, coords, align_corners, padding)
    if torch.is_grad_enabled() and any(f.requires_grad for f in factors):
        return _HexRankSum.apply(corners, int(rank), *factors)
    return _hex_read(factors, corners, int(rank))
