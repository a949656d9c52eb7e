"""numba, where installed: the simulator's compiled loops are written once, here decorated.

``njit`` compiles with the options every kernel of the simulator uses: cached next to
the module (compiled once per machine, a few seconds), ``error_model="numpy"`` (a
division by zero gives inf/NaN as in numpy, not an exception), no GIL.

:func:`njit_borrowing` also turns off numba's reference counting of arrays (NRT) for a
hot loop that only reads and writes arrays it is given: every array variable a loop
binds -- an argument of an inlined helper, a slice -- otherwise costs an atomic
increment and decrement per pass (measured: a third of the event core's own time). Such
a function may not create arrays; its caller allocates the scratch space. Without numba
the functions stay plain Python and :data:`AVAILABLE` is ``False``: callers then take
their numpy path.

numba keys a function's cache on its own file's modification time and size only. A
kernel that inlines a helper from another module would keep its stale machine code after
an edit of that helper alone, and silently give the old results. So the compiled modules
(:data:`SOURCES`) are hashed together on import, and their caches are dropped whenever
the hash changes (:func:`drop_stale_cache`). This covers numba's default cache location
beside the module; a cache moved elsewhere with ``NUMBA_CACHE_DIR`` is not watched.
"""

from __future__ import annotations

import hashlib
import itertools
from collections.abc import Callable, Sequence
from pathlib import Path

from eventrecon.render.compiled import (
    AVAILABLE,
    GRAIN,
    OPTIONS,
    compiled_parallel,
    numba_threads,
    parts,
    prange,
)

try:
    import numba
except ImportError:                              # pragma: no cover - numba is a dependency
    numba = None

__all__ = ["AVAILABLE", "SOURCES", "drop_stale_cache", "njit", "njit_borrowing",
           "njit_inline", "njit_parallel", "larger", "smaller", "numba_threads", "parts",
           "prange", "GRAIN"]

#: The modules of this package whose compiled functions call (inline) one another, and
#: ``crossing.py``, whose constants the compiled crossing time reads.
SOURCES = ("jit.py", "compiled_paths.py", "compiled_core.py", "merge.py", "crossing.py")


def drop_stale_cache(package: Path = Path(__file__).parent,
                     sources: Sequence[str] = SOURCES,
                     decorators: Path = Path(__file__)) -> bool:
    """Delete numba's cache files in ``package/__pycache__`` unless they were made from
    the ``sources`` (file names in ``package``; this package's :data:`SOURCES` by default)
    and the ``decorators`` (this file: how every kernel and helper is compiled) as they
    are now (a SHA-1 of them all, kept beside the cache). Returns whether anything was
    dropped. A read-only package is left as it is. Another package whose kernels inline
    one another's helpers calls it on import with its own files."""
    cache = package / "__pycache__"
    files = [package / name for name in sources] + [decorators]
    digest = hashlib.sha1(b"".join(f.read_bytes() for f in files
                                   if f.exists())).hexdigest()
    stamp = cache / "numba_sources.sha1"
    try:
        if stamp.read_text() == digest:
            return False
    except OSError:
        pass
    try:
        stale = list(itertools.chain(cache.glob("*.nbi"), cache.glob("*.nbc")))
        for f in stale:
            f.unlink(missing_ok=True)
        cache.mkdir(exist_ok=True)
        stamp.write_text(digest)
    except OSError:                              # read-only install: numba recompiles
        return False                             # or uses what it has
    return bool(stale)


if AVAILABLE:
    drop_stale_cache()


def njit(fn: Callable, inline: bool = False, nrt: bool = True) -> Callable:
    """``fn`` compiled (see the module docstring); ``inline``: at its call sites, for
    small per-element helpers whose call would cost more than their work; ``nrt=False``:
    without reference counting (:func:`njit_borrowing`).

    An inline helper is compiled once, without reference counting (it may not create
    arrays), and marked ``alwaysinline`` for LLVM (numba's ``forceinline``), which copies
    its optimised code into each caller. numba's own ``inline="always"`` instead copies
    the helper's IR into every call site and types it again there. Both run the same
    operations in the same order, so they give the same bits. Measured in one process
    with both builds alternated (session 66, 2 threads), HexPlane's fused rank sum ran
    0.90× as long with LLVM's inlining, TensoRF-CP's 0.97–0.99× and NGP's hash
    encoding 0.99×; the first compile took about as long."""
    if numba is None:                            # pragma: no cover
        return fn
    if inline:
        return numba.njit(**OPTIONS, _nrt=False, forceinline=True)(fn)
    return numba.njit(**OPTIONS, _nrt=nrt)(fn)


def njit_inline(fn: Callable) -> Callable:
    """:func:`njit` with ``inline=True`` (a decorator)."""
    return njit(fn, inline=True)


def njit_borrowing(fn: Callable) -> Callable:
    """:func:`njit` with ``nrt=False`` (a decorator; see the module docstring)."""
    return njit(fn, nrt=False)


@njit_inline
def larger(a, b):
    """``max(a, b)`` of two scalars, inlined: numba compiles the builtin as a function of
    its own that LLVM leaves out of line, and each call in a loop spills the caller's
    floating-point registers. The builtin's rule: ``a`` unless ``b > a`` (``NaN`` in
    ``b`` gives way)."""
    return b if b > a else a


@njit_inline
def smaller(a, b):
    """``min(a, b)`` of two scalars, inlined (:func:`larger`): ``a`` unless ``b < a``."""
    return b if b < a else a


#: :func:`~eventrecon.render.compiled.compiled_parallel`: ``parallel=True``, its ``prange``
#: loop on numba's threads (the loops it splits, :func:`parts`).
njit_parallel = compiled_parallel
