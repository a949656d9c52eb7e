"""numba for the compiled loops outside the simulator: the decorators, and how many of
numba's threads a loop may take (:func:`parts`, which the simulator's helpers use too).

The simulator's :mod:`eventrecon.sim.jit` builds on this module (its decorators add
inlining and a stale-cache check over its own files); this package may not import that
one: the simulator imports the renderer's cameras, and subpackages must not import one
another in a cycle (``tests/test_structure.py``). That stale-cache check does not cover
these files: numba keys a function's cache on its own file alone, so each module here
keeps its compiled loops self-contained (no compiled helper from another module) and
passes values that may change as arguments, not globals.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

try:
    import numba
except ImportError:                              # pragma: no cover - numba is a dependency
    numba = None

#: ``numba.prange`` (``range`` without numba): the parallel loop of :func:`compiled_parallel`.
prange = range if numba is None else numba.prange

__all__ = ["AVAILABLE", "GRAIN", "OPTIONS", "compiled", "compiled_parallel", "numba_threads",
           "parts", "prange"]

#: Whether numba could be imported (else the compiled paths decline and PyTorch's run).
AVAILABLE = numba is not None
#: The options of every compiled loop: cached beside its file, NumPy's error model (a
#: division by zero gives inf/NaN), no GIL.
OPTIONS = {"cache": True, "error_model": "numpy", "nogil": True}
#: Items per range, at least, when :func:`parts` splits a loop between threads.
GRAIN = 4096


def compiled(fn: Any) -> Any:
    """``fn`` compiled with the options of the simulator's loops
    (:func:`eventrecon.sim.jit.njit_borrowing`: :data:`OPTIONS` and no reference
    counting, so the loop may not create arrays: its caller allocates them). Without
    numba, ``fn`` itself."""
    if numba is None:                            # pragma: no cover
        return fn
    return numba.njit(**OPTIONS, _nrt=False)(fn)


def compiled_parallel(fn: Any) -> Any:
    """``fn`` compiled with :data:`OPTIONS` and ``parallel=True``: its ``prange`` loop
    runs on numba's threads (the ranges it is given, :func:`parts`)."""
    if numba is None:                            # pragma: no cover
        return fn
    return numba.njit(**OPTIONS, parallel=True)(fn)


def numba_threads() -> int:
    """numba's thread count (``NUMBA_NUM_THREADS``: the CPU's cores unless set); 1
    without numba."""
    return 1 if numba is None else int(numba.config.NUMBA_NUM_THREADS)


@functools.cache
def _thread_safe_layer() -> bool:
    """Whether numba's threading layer is OpenMP or TBB (launched once, on a trivial
    loop, to find out). Its ``workqueue`` fallback aborts the process when two Python
    threads enter parallel code at once, so then nothing is split."""
    if numba is None:                            # pragma: no cover
        return False
    try:
        _probe(np.zeros(2))
        return numba.threading_layer() in ("omp", "tbb")
    except (ValueError, RuntimeError):           # pragma: no cover - no layer loads
        return False


def parts(n: int, grain: int = GRAIN) -> int:
    """How many ranges to split ``n`` independent items into for a
    :func:`compiled_parallel` loop: ``min(torch threads, numba threads, n // grain)``, at
    least 1 (1: call the serial loop instead; also where numba's threading layer is not
    thread-safe). When more than 1, sets numba's thread count of the calling thread to it.

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


@compiled_parallel
def _probe(a: Any) -> None:
    """A trivial parallel loop (:func:`_thread_safe_layer`)."""
    for i in prange(a.shape[0]):
        a[i] += 1.0
