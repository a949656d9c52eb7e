"""The one set of numba decorators of :mod:`eventrecon.kernels`, and how many of numba's
threads a kernel's loop may take.

Every kernel is compiled with :data:`OPTIONS`: cached beside its file (compiled once per
machine), NumPy's error model (a division by zero gives inf/NaN, not an exception), no
GIL. Three decorators:

- :func:`serial`: a loop without numba's reference counting of arrays (NRT). Every
  array a loop binds (an argument of an inlined helper, a slice) would otherwise cost an
  atomic increment and decrement per pass. Such a function may not create arrays: its
  caller allocates the scratch space.
- :func:`parallel`: ``parallel=True``; its :data:`prange` loop runs on numba's threads,
  over the ranges :func:`parts` chooses.
- :func:`inline`: a small per-element helper, compiled without NRT and marked
  ``alwaysinline`` for LLVM (numba's ``forceinline``), which copies its optimised code
  into each caller.

numba keys a cached function on its own file (modification time and size) and its own
bytecode only, not on the helpers it calls nor on these options. So each kernel module
is self-contained: the compiled helpers it calls live in the same file, and an edit of
one helper re-stamps the file that inlines it. This module holds no compiled kernel or
helper (only the threading-layer probe of :func:`parts`, compiled on its first use) and
does nothing on import. After changing :data:`OPTIONS` or a decorator, delete the
kernels' cache files (``src/eventrecon/kernels/__pycache__/*.nbi``, ``*.nbc``).
Without numba the decorators return the plain Python function and :data:`AVAILABLE` is
``False``: callers then take their PyTorch reference.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np

try:
    import numba
except ImportError:                              # pragma: no cover - numba is a dependency
    numba = None

__all__ = ["AVAILABLE", "GRAIN", "OPTIONS", "inline", "numba_threads", "parallel", "parts",
           "prange", "serial"]

#: Whether numba could be imported (else every kernel declines and PyTorch runs).
AVAILABLE = numba is not None
#: The options of every kernel: cached beside its file, NumPy's error model, no GIL.
OPTIONS = {"cache": True, "error_model": "numpy", "nogil": True}
#: Items per range, at least, when :func:`parts` splits a loop between threads.
GRAIN = 4096
#: ``numba.prange`` (``range`` without numba): the loop :func:`parallel` splits.
prange = range if numba is None else numba.prange


def serial(fn: Callable) -> Callable:
    """``fn`` compiled with :data:`OPTIONS`, without reference counting (it may not
    create arrays). Without numba, ``fn`` itself."""
    if numba is None:                            # pragma: no cover
        return fn
    return numba.njit(**OPTIONS, _nrt=False)(fn)


def parallel(fn: Callable) -> Callable:
    """``fn`` compiled with :data:`OPTIONS` and ``parallel=True``: its :data:`prange`
    loop runs on numba's threads. Without numba, ``fn`` itself."""
    if numba is None:                            # pragma: no cover
        return fn
    return numba.njit(**OPTIONS, parallel=True)(fn)


def inline(fn: Callable) -> Callable:
    """``fn`` compiled with :data:`OPTIONS`, without reference counting, and inlined by
    LLVM at each call site (``forceinline``). Without numba, ``fn`` itself."""
    if numba is None:                            # pragma: no cover
        return fn
    return numba.njit(**OPTIONS, _nrt=False, forceinline=True)(fn)


def numba_threads() -> int:
    """numba's thread count (``NUMBA_NUM_THREADS``: the CPU's cores unless set); 1
    without numba.

    >>> numba_threads() >= 1
    True
    """
    return 1 if numba is None else int(numba.config.NUMBA_NUM_THREADS)


def _probe(a: Any) -> None:
    """A trivial parallel loop, compiled on first use by :func:`_thread_safe_layer`."""
    for i in prange(a.shape[0]):
        a[i] += 1.0


@functools.cache
def _thread_safe_layer() -> bool:
    """Whether numba's threading layer is OpenMP or TBB (found by running a trivial
    parallel loop once). Its ``workqueue`` fallback aborts the process when two Python
    threads enter parallel code at once, so then nothing is split."""
    if numba is None:                            # pragma: no cover
        return False
    try:
        parallel(_probe)(np.zeros(2))
        return numba.threading_layer() in ("omp", "tbb")
    except (ValueError, RuntimeError):           # pragma: no cover - no layer loads
        return False


def parts(n: int, grain: int = GRAIN) -> int:
    """How many ranges to split ``n`` independent items into for a :func:`parallel`
    loop: ``min(torch threads, numba threads, n // grain)``, at least 1 (1: call the
    serial loop instead; also where numba's threading layer is not thread-safe). When
    more than 1, sets numba's thread count of the calling thread to it.

    >>> parts(10)
    1
    """
    if numba is None:                            # pragma: no cover
        return 1
    import torch

    k = max(1, min(torch.get_num_threads(), numba_threads(), n // grain))
    if k > 1 and not _thread_safe_layer():
        return 1
    if k > 1:
        numba.set_num_threads(k)
    return k
