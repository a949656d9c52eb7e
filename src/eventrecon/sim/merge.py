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

With numba (:mod:`~eventrecon.sim.jit`) the same order comes from compiled bucket
sorts instead (:func:`_bucket_order`): a stable counting sort into up to 4096 equal-time
buckets, each bucket (cache-sized) again into buckets of about ``FINE`` events, and the
bucket then ordered by ``(t, g)`` with one stable insertion pass (a stable merge sort
first where a fine bucket holds more than 48). The bucket index
``⌊(t − lo)·B/(hi − lo)⌋`` is monotone in ``t``, so equal stamps share a bucket and the
buckets follow in time: the insertion pass only moves an event inside its fine bucket.
Large arrays are touched a few times instead of a dozen. The one extra column of the
core's events (the polarity, ``int8``) is carried along by the sorts instead of a 64-bit
permutation gathered afterwards: 7 bytes less per event to write, and no random-access
gather.
"""

from __future__ import annotations

import numpy as np

from eventrecon.sim.jit import AVAILABLE, larger, njit, smaller

__all__ = ["time_order", "merge_by_time"]

#: Chunk size of the coarse pass (events); below ``4·CHUNK`` one chunk is used.
CHUNK = 1 << 15
#: Events per fine bucket of the compiled order, on average (:func:`_order_buckets`).
FINE = 1


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


@njit
def _count(t, lo, scale, B, start):
    """Add the bucket sizes of ``t`` (``⌊(t − lo)·scale⌋``, at most ``B − 1``) to
    ``start[1:]``."""
    for i in range(t.size):
        start[larger(smaller(np.int64((t[i] - lo) * scale), B - 1), 0) + 1] += 1


@njit
def _place(t, g, q, index, first, lo, scale, B, pos, ts, gs, qs):
    """Stable counting-sort placement of ``(t, g)`` with their payload at the running
    bucket positions ``pos``: the index ``first + i`` where ``index``, else ``q[i]``
    (two stores, so that each keeps its own integer or float type)."""
    for i in range(t.size):
        k = larger(smaller(np.int64((t[i] - lo) * scale), B - 1), 0)
        j = pos[k]
        ts[j], gs[j] = t[i], g[i]
        if index:
            qs[j] = first + i
        else:
            qs[j] = q[i]
        pos[k] += 1


@njit
def _insertion(ts, gs, ps, a, e):
    """Stable insertion sort of ``ts, gs, ps[a:e]`` by ``(t, g)``, in place: linear on a
    range that is already in order but for short runs (a bucket after its fine pass)."""
    for i in range(a + 1, e):
        x, y, z = ts[i], gs[i], ps[i]
        j = i
        while j > a and (ts[j - 1] > x or (ts[j - 1] == x and gs[j - 1] > y)):
            ts[j], gs[j], ps[j] = ts[j - 1], gs[j - 1], ps[j - 1]
            j -= 1
        ts[j], gs[j], ps[j] = x, y, z


@njit
def _order_small(ts, gs, ps, a, e):
    """``ts, gs, ps[a:e]`` ordered in place by ``(t, g)``, stably."""
    if e - a > 48:
        o = np.argsort(gs[a:e], kind="mergesort")
        o = o[np.argsort(ts[a:e][o], kind="mergesort")]
        ts[a:e], gs[a:e], ps[a:e] = ts[a:e][o], gs[a:e][o], ps[a:e][o]
        return
    _insertion(ts, gs, ps, a, e)


@njit
def _order_buckets(ts, gs, ps, start):
    """Order each coarse bucket ``[start[k], start[k+1])`` of ``ts, gs, ps`` in place:
    again into about ``m/FINE`` equal-time buckets (in cache), the few with more than 48
    events (equal stamps) by a merge sort, then the whole bucket by one insertion pass,
    which only moves events inside their fine bucket (the fine buckets follow in time)."""
    m_max = 0
    for k in range(start.size - 1):
        m_max = larger(m_max, start[k + 1] - start[k])
    s2 = np.zeros(m_max // FINE + 2, np.int64)
    ts2, gs2, ps2 = np.empty(m_max), np.empty(m_max, gs.dtype), np.empty(m_max, ps.dtype)
    for k in range(start.size - 1):
        a, e = start[k], start[k + 1]
        m = e - a
        if m < 2:
            continue
        lo, hi = ts[a:e].min(), ts[a:e].max()
        B, scale = m // FINE, (m // FINE) / (hi - lo)
        if m <= 48 or not hi > lo or not np.isfinite(scale):   # (subnormal spread)
            _order_small(ts, gs, ps, a, e)
            continue
        s2[:B + 1] = 0
        _count(ts[a:e], lo, scale, B, s2)
        for j in range(B):
            s2[j + 1] += s2[j]
        pos = s2[:B].copy()
        _place(ts[a:e], gs[a:e], ps[a:e], False, 0, lo, scale, B, pos, ts2, gs2, ps2)
        for j in range(B):
            if s2[j + 1] - s2[j] > 48:
                _order_small(ts2, gs2, ps2, s2[j], s2[j + 1])
        _insertion(ts2, gs2, ps2, 0, m)
        ts[a:e], gs[a:e], ps[a:e] = ts2[:m], gs2[:m], ps2[:m]


def _carried(parts: list[tuple[np.ndarray, ...]]) -> bool:
    """Whether the one extra column of ``(g, t, q)`` parts (lengths already checked by
    :func:`merge_by_time`) can travel with the events: 1-D arrays of one integer, bool or
    float32/64 dtype. Any other column (several, 2-D, dates, strings, half floats) is
    gathered by the order instead."""
    if len(parts[0]) != 3:
        return False
    qs = [p[2] for p in parts]
    return (all(isinstance(q, np.ndarray) and q.ndim == 1 for q in qs)
            and len({q.dtype for q in qs}) == 1
            and (qs[0].dtype.kind in "iub" or qs[0].dtype in (np.float32, np.float64)))


def _compiled_fits(ts: list[np.ndarray], gs: list[np.ndarray]) -> bool:
    """Whether the compiled order applies: numba, more than ``4·CHUNK`` events, float64
    stamps and one integer dtype of pixel ids (the numpy path keeps any other dtypes)."""
    return (AVAILABLE and sum(t.size for t in ts) > 4 * CHUNK
            and all(isinstance(t, np.ndarray) and t.dtype == np.float64 for t in ts)
            and all(isinstance(g, np.ndarray) for g in gs)
            and len({g.dtype for g in gs}) == 1 and gs[0].dtype.kind in "iu")


def _bucket_order(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]]
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(q[perm], t[perm], g[perm])`` of the concatenated ``(t, g, q)`` parts (finite
    ``t``), ``perm = np.lexsort((g, t))`` (module docstring); the parts are read in place.

    ``q`` is the payload carried along: one column of the same dtype in every part, or
    ``None`` in every part for the permutation itself (``q[perm]`` is then ``perm``)."""
    n = sum(t.size for t, _, _ in parts)
    lo = min(t.min() for t, _, _ in parts if t.size)
    hi = max(t.max() for t, _, _ in parts if t.size)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise ValueError("time order: expected finite time stamps, got NaN or inf")
    qdt = np.int64 if parts[0][2] is None else parts[0][2].dtype
    ts, gs, qs = np.empty(n), np.empty(n, parts[0][1].dtype), np.empty(n, qdt)
    B = min(max(1, n // 16384), 4096) if hi > lo else 1
    scale = B / (hi - lo) if hi > lo else 0.0
    if not np.isfinite(scale):                   # a subnormal spread: one bucket
        B, scale = 1, 0.0
    start = np.zeros(B + 1, np.int64)
    for t, _, _ in parts:
        _count(t, lo, scale, B, start)
    np.cumsum(start, out=start)
    pos, first, none = start[:-1].copy(), 0, np.zeros(0, np.int64)
    for t, g, q in parts:
        _place(t, g, none if q is None else q, q is None, first, lo, scale, B, pos, ts, gs, qs)
        first += t.size
    _order_buckets(ts, gs, qs, start)
    return qs, ts, gs


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
    if _compiled_fits([t], [g]):
        return _bucket_order([(t, g, None)])[0]
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
    into coarse time buckets, then each bucket is ordered in place (in cache); with
    numba, a single extra column travels with the events through both passes.

    >>> g, t, p = merge_by_time([(np.array([1, 2]), np.array([.5, .1]), np.array([1, -1])),
    ...                          (np.array([0]), np.array([.5]), np.array([1]))])
    >>> g.tolist(), t.tolist(), p.tolist()
    ([2, 0, 1], [0.1, 0.5, 0.5], [-1, 1, 1])
    """
    for k, part in enumerate(parts):
        if len({len(c) for c in part}) > 1:
            raise ValueError(f"merge_by_time: part {k} has columns of lengths "
                             f"{[len(c) for c in part]}; expected one length per part")
    if _compiled_fits([p[1] for p in parts], [p[0] for p in parts]):
        if _carried(parts):
            q, t, g = _bucket_order([(p[1], p[0], p[2]) for p in parts])
            return g, t, q                       # the one extra column carried along
        perm, t, g = _bucket_order([(part[1], part[0], None) for part in parts])
        rest = (np.concatenate([part[i] for part in parts]) for i in range(2, len(parts[0])))
        return (g, t, *(c[perm] for c in rest))
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
