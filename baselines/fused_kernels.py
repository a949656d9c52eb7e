"""The per-point pieces of the factorised backbones' fused rank sums (TensoRF-CP's
:mod:`baselines.cp_fused`, HexPlane's :mod:`baselines.hex_fused`), compiled inline into
their kernels, and the split of their passes between threads.

A factor is stored channel-last (:func:`baselines.interp.channel_rows`: ``[rows, C]``,
``C = F·R`` channels) and read at a point's lower vertex ``i`` and weights ``(u, v)``
per axis (:func:`baselines.interp.vertex_corners`). Each sample is summed as
:mod:`baselines.interp` sums it -- a fill of 0 (NaN where a weight is NaN, i.e. a
non-finite coordinate), plus each corner inside the factor in corner order -- so a fused
kernel's gradients are the factor-by-factor path's to the bit on one thread.

The fused kernels inline these helpers, and numba keys a kernel's cache on its own file
only, so the three files (:data:`SOURCES`) are hashed together on import, and when one
changes every numba cache file of ``baselines/`` is dropped (the other modules' kernels
too: they compile again once; :func:`eventrecon.sim.jit.drop_stale_cache`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

import eventrecon.sim.jit as jit
from eventrecon.sim.jit import AVAILABLE, drop_stale_cache, njit_inline

__all__ = ["PAD", "SOURCES", "axpy", "line_sample", "line_vertices", "rank_sums",
           "run_forward", "scatter_copies", "supported_factors"]

#: The modules whose compiled kernels inline one another's helpers.
SOURCES = ("fused_kernels.py", "cp_fused.py", "hex_fused.py")

#: Unused channels at the end of each range's scratch rows, so that two threads never
#: write one cache line (64 bytes, 16 float32).
PAD = 16

if AVAILABLE:
    drop_stale_cache(Path(__file__).parent, SOURCES)


@njit_inline
def line_vertices(lower: Any, weights: Any, sizes: Any, n: int, a: int
                  ) -> tuple[int, int, Any, Any, bool, bool]:
    """Point ``n``'s two vertices along column ``a`` of ``lower, weights`` (a line of
    ``sizes[a]`` vertices): their rows, weights and whether each lies inside."""
    i = lower[n, a]
    return (i, i + 1, weights[n, a, 0], weights[n, a, 1], 0 <= i < sizes[a],
            0 <= i + 1 < sizes[a])


@njit_inline
def line_sample(T: Any, i: int, j: int, u: Any, v: Any, in_i: bool, in_j: bool, s: Any,
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


@njit_inline
def axpy(G: Any, row: int, w: Any, x: Any, a: int, inside: bool) -> None:
    """``G[row] += w · x[a]`` over the channels, for a vertex inside the factor."""
    if inside:
        for c in range(G.shape[1]):
            G[row, c] += w * x[a, c]


@njit_inline
def rank_sums(prod: Any, rank: int, c_all: int, out: Any, n: int) -> None:
    """``out[n, f] = Σ_r prod[f·R + r]``, each sum from ``r = 0`` up. With four features
    (the full field) the four sums run side by side, the same order, so that one sum's
    additions do not each wait for the one before (TensoRF-CP's pass 0.8x as long at
    39 040 points)."""
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


def run_forward(kernel: Any, kernel_parts: Any, args: tuple, n_points: int, n_factors: int,
                channels: int, dtype: Any) -> None:
    """A fused forward pass over ``n_points``: ``kernel(*args, s, acc)`` with scratch
    ``s [n_factors, C]`` and ``acc [C]``, or, where the points split into ``P > 1``
    ranges (:func:`eventrecon.sim.jit.parts`), ``kernel_parts`` with each range's
    scratch padded apart (:data:`PAD`)."""
    p = jit.parts(n_points)
    if p == 1:
        kernel(*args, np.empty((n_factors, channels), dtype), np.empty(channels, dtype))
    else:
        kernel_parts(*args, np.empty((p, n_factors, channels + PAD), dtype),
                     np.empty((p, channels + PAD), dtype))


def scatter_copies(n_points: int, tables: list[np.ndarray], dtype: torch.dtype,
                   corners: int) -> list[Tensor]:
    """Zeroed gradients ``[P, rows, C]`` for each table, one copy per range of the
    points that the backward pass runs on its own thread (``corners``: the rows each
    point scatters into, over all tables). ``P`` ranges while each range's row writes
    (its points times ``corners``) are at least its copies' rows, and it has at least
    :data:`~eventrecon.sim.jit.GRAIN` points (:func:`eventrecon.sim.jit.parts`; the rule
    of :mod:`baselines.interp`'s scatter)."""
    rows = sum(t.shape[0] for t in tables)
    p = jit.parts(n_points, grain=max(jit.GRAIN, rows // max(corners, 1)))
    return [torch.zeros((p, *t.shape), dtype=dtype) for t in tables]


def supported_factors(factors: list[Tensor], coords: Tensor) -> bool:
    """The conditions both fused rank sums share: numba, factors of one channel count
    and one float32/float64 dtype on the CPU, coordinates ``[N, 4]`` of that dtype on the
    CPU that need no gradient."""
    return (AVAILABLE and len({f.shape[0] for f in factors}) == 1
            and coords.dim() == 2 and coords.shape[1] == 4
            and coords.dtype in (torch.float32, torch.float64)
            and coords.device.type == "cpu"
            and all(f.device.type == "cpu" and f.dtype == coords.dtype for f in factors)
            and not (coords.requires_grad and torch.is_grad_enabled()))
