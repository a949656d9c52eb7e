"""Short rows sorted by a sorting network run across the rows at once (CPU, compiled).

The fine level sorts its ``K_f`` uniform draws per ray (:func:`~.samplers.sample_pdf`);
``torch.sort`` on ``[n, 32]`` rows took ~0.25 ms per call here, about as long as
compositing them. A sorting network is a fixed list of compare-exchanges ``(i, j)``,
``i < j``: ``a_i, a_j ← min(a_i, a_j), max(a_i, a_j)``. Applied to the rows stored
transposed, ``[K, n]``, each compare-exchange is one vectorised pass of compares and
selects over the ``n`` rays (16 float32 lanes per instruction with AVX-512), plus two
transposes.

The network is Batcher's odd-even merge sort for the next power of two ``P ≥ K``
(``P/4 · log₂P · (log₂P − 1) + P − 1`` compare-exchanges, 191 for ``K = 32``). A row
padded with ``+∞`` to ``P`` keeps the padding at the end, so every compare-exchange that
touches an index ``≥ K`` leaves the row unchanged and is dropped. A compare-exchange
swaps only when ``a_j < a_i``, so each row stays a permutation of itself: for rows
without NaN the result is the values ``torch.sort`` returns, bit for bit, up to the
order of ``−0`` and ``+0``, which compare equal (``torch.sort`` promises no order for
them either). A NaN is never swapped, so it stays where it is (``torch.sort`` puts it
last).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import torch
from torch import Tensor

from eventrecon.render.compiled import AVAILABLE, compiled, compiled_parallel, parts, prange

__all__ = ["network", "sort_rows"]

#: Rays per range, at least, when the passes are split between threads.
RAYS_PER_RANGE = 2048


@functools.cache
def network(k: int) -> np.ndarray:
    """Batcher's odd-even merge sort for ``k`` keys: ``[E, 2]`` int64 pairs ``(i, j)``,
    ``i < j``, in the order they are applied (the module docstring)."""
    size = 1 << max(k - 1, 0).bit_length()
    pairs = []
    p = 1
    while p < size:
        step = p
        while step >= 1:
            for j in range(step % p, size - step, 2 * step):
                for i in range(min(step, size - j - step)):
                    a, b = i + j, i + j + step
                    if a // (2 * p) == b // (2 * p) and b < k:
                        pairs.append((a, b))
            step //= 2
        p *= 2
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


@compiled
def _exchange(cols: Any, pairs: Any, a: int, b: int) -> None:
    """Each compare-exchange of ``pairs [E, 2]`` on columns ``a … b − 1`` of ``cols
    [K, n]`` (the rows sorted, transposed): a swap where the second key is smaller."""
    for e in range(pairs.shape[0]):
        lo, hi = cols[pairs[e, 0], a:b], cols[pairs[e, 1], a:b]   # (a loop from a to b
        for r in range(lo.shape[0]):                                # ran 5x slower)
            x, y = lo[r], hi[r]
            lo[r] = y if y < x else x            # MINPS / MAXPS: with y < x the two swap;
            hi[r] = x if x > y else y            # equal keys and NaNs stay where they are


@compiled_parallel
def _exchange_parts(cols: Any, pairs: Any, p: int) -> None:
    """:func:`_exchange` on ``p`` equal ranges of the columns of ``cols`` at once."""
    n = cols.shape[1]
    for k in prange(p):
        _exchange(cols, pairs, n * k // p, n * (k + 1) // p)


def sort_rows(x: Tensor) -> Tensor:
    """Each row of ``x [n, K]`` sorted ascending, as a new contiguous tensor: float32 or
    float64 on the CPU without gradient in compiled passes (the module docstring; the
    values of ``x.sort(dim=-1).values`` for rows without NaN), ``torch.sort`` otherwise."""
    if not (AVAILABLE and x.dim() == 2 and x.device.type == "cpu"
            and x.dtype in (torch.float32, torch.float64) and not x.requires_grad):
        return x.sort(dim=-1).values.contiguous()
    n, k = x.shape
    cols = torch.empty((k, n), dtype=x.dtype)    # a copy: x itself is left as it is
    cols.copy_(x.t())
    p = parts(n, RAYS_PER_RANGE)
    if p == 1:
        _exchange(cols.numpy(), network(k), 0, n)
    else:
        _exchange_parts(cols.numpy(), network(k), p)
    return cols.t().contiguous()
