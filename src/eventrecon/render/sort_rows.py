"""Short rows sorted by a sorting network run across the rows at once (CPU, compiled).

The fine level sorts its ``K_f`` uniform draws per ray (:func:`~.samplers.sample_pdf`);
``torch.sort`` on ``[n, 32]`` rows took ~0.25 ms per call here, about as long as
compositing them. A sorting network is a fixed list of compare-exchanges ``(i, j)``,
``i < j``: ``a_i, a_j ← min(a_i, a_j), max(a_i, a_j)``. Applied to the rows stored
transposed, ``[K, n]``, each compare-exchange is one pass of vector ``min``/``max`` over
the ``n`` rays, so the whole sort is ``|network| · n / 16`` vector operations plus two
transposes.

The network is Batcher's odd-even merge sort for the next power of two ``P ≥ K``
(``P/4 · log₂P · (log₂P − 1) + P − 1`` compare-exchanges, 191 for ``K = 32``). A row
padded with ``+∞`` to ``P`` keeps the padding at the end, so every compare-exchange that
touches an index ``≥ K`` leaves the row unchanged and is dropped. The result is the
values ``torch.sort`` returns, bit for bit, for rows without NaN (the sorted values of a
row do not depend on how ties are ordered; ``±0`` compare equal and may come out in
either order, which ``torch.sort`` does not promise either).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
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
def _exchange(cols: Any, pairs: Any) -> None:
    """Each compare-exchange of ``pairs [E, 2]`` on the columns ``cols [K, m]``."""
    for e in range(pairs.shape[0]):
        lo, hi = cols[pairs[e, 0]], cols[pairs[e, 1]]
        for r in range(lo.shape[0]):
            a, b = lo[r], hi[r]
            lo[r] = min(a, b)
            hi[r] = max(a, b)


@compiled_parallel
def _exchange_parts(cols: Any, pairs: Any, p: int) -> None:
    """:func:`_exchange` on ``p`` equal ranges of the rows (columns of ``cols``) at once."""
    n = cols.shape[1]
    for k in prange(p):
        a, b = n * k // p, n * (k + 1) // p
        _exchange(cols[:, a:b], pairs)


def sort_rows(x: Tensor) -> Tensor:
    """Each row of the float ``x [n, K]`` (CPU, no NaN) sorted ascending: a new
    contiguous tensor, the values of ``x.sort(dim=-1).values``. Without numba, or for
    other tensors, ``torch.sort``."""
    if not (AVAILABLE and x.dim() == 2 and x.device.type == "cpu" and x.is_floating_point()
            and not x.requires_grad):
        return x.sort(dim=-1).values.contiguous()
    cols = x.t().contiguous()                    # [K, n]
    p = parts(x.shape[0], RAYS_PER_RANGE)
    if p == 1:
        _exchange(cols.numpy(), network(x.shape[1]))
    else:
        _exchange_parts(cols.numpy(), network(x.shape[1]), p)
    return cols.t().contiguous()
