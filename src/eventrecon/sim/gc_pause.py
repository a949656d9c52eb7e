"""Python's cyclic garbage collector, paused around the event core's loops.

The core's loops allocate a few hundred small containers per iteration (the tuples the
compiled kernels return, generator frames), which start a young-generation collection
every 700 allocations and now and then a full one. A full collection walks every object
the process holds -- numpy, numba, torch when imported -- and the core creates no
reference cycles for it to find. On the 346×260 grating at θ = 0.5 (``python -m
benchmarks sim``), the collections cost 2-4 % of the run (measured alternated in one
process, ``docs/results/event_core.md``, session 42). Reference counting still frees
every temporary at once; only the cycle search waits until the loop ends, and with it
any cycles the caller's signal creates (a rendered signal's few objects per call).
"""

from __future__ import annotations

import gc
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["gc_paused"]


@contextmanager
def gc_paused() -> Iterator[None]:
    """Disable the cyclic collector inside the block; restore its previous state after,
    also when the block raises (a collector disabled by the caller stays disabled)."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()
