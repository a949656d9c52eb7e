"""numba, where installed: the simulator's compiled loops are written once, here decorated.

``njit`` compiles with the options every kernel of the simulator uses: cached next to
the module (compiled once per machine, a few seconds), ``error_model="numpy"`` (a
division by zero gives inf/NaN as in numpy, not an exception), no GIL. Without numba
the functions stay plain Python and :data:`AVAILABLE` is ``False``: callers then take
their numpy path.
"""

from __future__ import annotations

from collections.abc import Callable

try:
    import numba
except ImportError:                              # pragma: no cover - numba is a dependency
    numba = None

__all__ = ["AVAILABLE", "njit", "njit_inline"]

#: Whether numba could be imported.
AVAILABLE = numba is not None


def njit(fn: Callable, inline: bool = False) -> Callable:
    """``fn`` compiled (see the module docstring); ``inline``: at its call sites, for
    small per-element helpers whose call would cost more than their work."""
    if numba is None:                            # pragma: no cover
        return fn
    return numba.njit(cache=True, error_model="numpy", nogil=True,
                      inline="always" if inline else "never")(fn)


def njit_inline(fn: Callable) -> Callable:
    """:func:`njit` with ``inline=True`` (a decorator)."""
    return njit(fn, inline=True)
