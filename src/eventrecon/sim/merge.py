"""Time order of event streams without a comparison sort: :func:`time_order`.

The simulator emits each pixel's events in time order, but the pixels interleave. The
published order is by time ``t`` (float64), ties by pixel ``g``, ties of both in input
order -- exactly ``np.lexsort((g, t))``. A comparison sort of ``E`` float64 keys costs
``O(E log E)`` with a large constant (about 100 ns per event at a few million); here it
is replaced by counting sorts on integer keys (numpy's stable sort of 16-bit keys is a
radix sort, a few ns per element):

1. a coarse bucket ``⌊(t − t_min)/(t_max − t_min)·B⌋``, ``B ≤ 255`` (one 8-bit counting
   sort) cuts the events into chunks of about ``2^15`` (more beyond 8 M events);
2. in each chunk a 32-bit key ``q = ⌊(t − t_lo)·(2^32 − 1)/(t_hi − t_lo)⌋`` is sorted by
   two 16-bit passes (least significant first, both stable);
3. ``q`` is monotone in ``t`` (rounded subtraction and scaling by a positive constant
   are monotone), so only runs of equal ``q`` can be out of ``(t, g)`` order: those few
   events are ordered exactly with ``np.lexsort``.

The result is the permutation ``np.lexsort((g, t))`` gives, element for element.
"""

from __future__ import annotations

import numpy as np

__all__ = ["time_order", "merge_by_time"]

#: Chunk size of the coarse pass (events); below ``4·CHUNK`` one chunk is used.
CHUNK = 1 << 15


def _radix32(q: np.ndarray) -> np.ndarray:
    """Stable argsort of ``q [n]`` uint32: two 16-bit counting-sort passes."""
    p1 = np.argsort((q & 0xFFFF).astype(np.uint16), kind="stable")
    p2 = np.argsort((q >> 16).astype(np.uint16)[p1], kind="stable")
    return p1[p2]


def _order_chunk(t: np.ndarray, g: np.ndarray) -> np.ndarray:
    """``np.lexsort((g, t))`` of one chunk (see the module docstring, steps 2-3)."""
    n = t.size
    if n < 2:
        return np.arange(n)
    lo, hi = t.min(), t.max()
    if not hi > lo:                              # one time stamp: by pixel, stably
        return np.argsort(g, kind="stable")
    q = ((t - lo) * ((2.0 ** 32 - 1) / (hi - lo))).astype(np.uint32)
    perm = _radix32(q)
    qs = q[perm]
    tie = np.flatnonzero(qs[1:] == qs[:-1])
    if tie.size:
        pos = np.union1d(tie, tie + 1)           # every member of a run of equal q
        sub = perm[pos]
        perm[pos] = sub[np.lexsort((g[sub], t[sub], qs[pos]))]
    return perm


def _buckets(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Coarse pass: ``(perm, bounds)`` grouping ``t`` into ``B = min(255, len(t)/CHUNK)``
    equal time buckets (stable), ``bounds [B + 1]`` the bucket starts in ``perm``."""
    lo, hi = t.min(), t.max()
    nb = min(255, max(1, t.size // CHUNK)) if hi > lo else 1
    scale = nb / (hi - lo) if hi > lo else 0.0
    b = np.minimum((t - lo) * scale, nb - 1).astype(np.uint8)   # one counting-sort pass
    bounds = np.zeros(nb + 1, np.int64)
    np.cumsum(np.bincount(b, minlength=nb), out=bounds[1:])
    return np.argsort(b, kind="stable"), bounds


def time_order(t: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Permutation ordering events by ``(t, g)``, stable: equal to ``np.lexsort((g, t))``.

    Args:
        t: ``[E]`` float64 finite time stamps.
        g: ``[E]`` integer pixel ids (the tie-break).

    Returns:
        ``[E]`` int64 permutation.

    >>> t = np.array([0.3, 0.1, 0.3, 0.2, 0.1])
    >>> g = np.array([5, 9, 2, 7, 1])
    >>> time_order(t, g).tolist(), np.lexsort((g, t)).tolist()
    ([4, 1, 3, 2, 0], [4, 1, 3, 2, 0])
    """
    t = np.asarray(t, dtype=np.float64)
    g = np.asarray(g)
    if t.size <= 4 * CHUNK:
        return _order_chunk(t, g).astype(np.int64, copy=False)
    perm, bounds = _buckets(t)
    ts, gs = t[perm], g[perm]
    for a, e in zip(bounds[:-1], bounds[1:]):
        if e - a > 1:
            perm[a:e] = perm[a:e][_order_chunk(ts[a:e], gs[a:e])]
    return perm


def merge_by_time(parts: list[tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
    """Concatenate event arrays ``(g, t, *rest)`` and order them by :func:`time_order`.

    ``parts``: tuples of equally long arrays, ``g`` first and ``t`` second. Returns the
    ordered concatenation (one array per tuple position). Large inputs are moved once
    into coarse time buckets, then each bucket is ordered in place (in cache).

    >>> g, t, p = merge_by_time([(np.array([1, 2]), np.array([.5, .1]), np.array([1, -1])),
    ...                          (np.array([0]), np.array([.5]), np.array([1]))])
    >>> g.tolist(), t.tolist(), p.tolist()
    ([2, 0, 1], [0.1, 0.5, 0.5], [-1, 1, 1])
    """
    cols = [np.concatenate([part[i] for part in parts]) for i in range(len(parts[0]))]
    if cols[1].size <= 4 * CHUNK:
        order = _order_chunk(cols[1], cols[0])
        return tuple(c[order] for c in cols)
    perm, bounds = _buckets(cols[1])
    cols = [c[perm] for c in cols]
    for a, e in zip(bounds[:-1], bounds[1:]):
        if e - a > 1:
            o = _order_chunk(cols[1][a:e], cols[0][a:e])
            for c in cols:
                c[a:e] = c[a:e][o]
    return tuple(cols)
