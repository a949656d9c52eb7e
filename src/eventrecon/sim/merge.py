"""Time order of event streams: :func:`time_order` and :func:`merge_by_time`.

The simulator emits each pixel's events in time order, but the pixels interleave. The
published order is by time ``t`` (float64), ties by pixel ``g``, ties of both in input
order: the permutation ``np.lexsort((g, t))`` (a stable sort by ``g``, then a stable
sort of that by ``t``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["time_order", "merge_by_time"]


def _check_finite(t: np.ndarray) -> None:
    """One clear error for a NaN or infinite stamp (no place in a time order)."""
    if not np.all(np.isfinite(t)):
        raise ValueError("time order: expected finite time stamps, got NaN or inf")


def time_order(t: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Permutation ordering events by ``(t, g)``, stable: ``np.lexsort((g, t))``.

    Args:
        t: ``[E]`` float64 finite time stamps.
        g: ``[E]`` integer pixel ids (the tie-break).

    Returns:
        ``[E]`` int64 permutation.

    Raises:
        ValueError: where a stamp is NaN or infinite.

    >>> t = np.array([0.3, 0.1, 0.3, 0.2, 0.1])
    >>> g = np.array([5, 9, 2, 7, 1])
    >>> time_order(t, g).tolist()
    [4, 1, 3, 2, 0]
    """
    t = np.asarray(t, dtype=np.float64)
    _check_finite(t)
    return np.lexsort((np.asarray(g), t)).astype(np.int64, copy=False)


def merge_by_time(parts: list[tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
    """Concatenate event arrays ``(g, t, *rest)`` and order them by :func:`time_order`.

    ``parts``: tuples of equally long arrays, ``g`` first and ``t`` second (finite).
    Returns the ordered concatenation, one array per tuple position, each of its parts'
    dtype.

    >>> g, t, p = merge_by_time([(np.array([1, 2]), np.array([.5, .1]), np.array([1, -1])),
    ...                          (np.array([0]), np.array([.5]), np.array([1]))])
    >>> g.tolist(), t.tolist(), p.tolist()
    ([2, 0, 1], [0.1, 0.5, 0.5], [-1, 1, 1])
    """
    for k, part in enumerate(parts):
        if len({len(c) for c in part}) > 1:
            raise ValueError(f"merge_by_time: part {k} has columns of lengths "
                             f"{[len(c) for c in part]}; expected one length per part")
    cols = [np.concatenate([part[i] for part in parts]) for i in range(len(parts[0]))]
    _check_finite(cols[1])
    order = np.lexsort((cols[0], cols[1]))
    return tuple(c[order] for c in cols)
