"""Keep freed memory inside the process, so that loops stop faulting the same pages in.

glibc's ``malloc`` unmaps a freed block above its mmap threshold (128 KiB at first,
raised on the fly up to 32 MiB) and trims the heap's top once more than twice that lies
free. A training step allocates and frees the same multi-MB activations every time, so
without a fixed threshold each step maps fresh pages and pays a page fault per 4 KiB
page, zeroing included. :func:`retain_freed_memory` fixes both thresholds with
``mallopt``: blocks up to :data:`MMAP_THRESHOLD` come from the heap and the heap is never
trimmed. Values are unchanged bit for bit; the process keeps its peak heap until it exits.

The command-line entry points call it (``train.py``, ``python -m eventrecon.evaluate``,
``python -m eventrecon.simulate``, ``python -m benchmarks``); ``EVENTRECON_MALLOC=default``
keeps glibc's behaviour. Without glibc (macOS, musl) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os

__all__ = ["MMAP_THRESHOLD", "TRIM_THRESHOLD", "retain_freed_memory"]

log = logging.getLogger(__name__)

#: Blocks up to this size come from the heap (glibc's ceiling for its dynamic threshold).
MMAP_THRESHOLD = 32 * 1024 * 1024
#: Free bytes at the heap's top before it is trimmed: the largest ``int``, i.e. never.
TRIM_THRESHOLD = 2 ** 31 - 1
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3       # glibc's <malloc.h>


def retain_freed_memory() -> bool:
    """Set glibc's mmap and trim thresholds (module docstring). Returns whether both were
    set: ``False`` without glibc or with ``EVENTRECON_MALLOC=default``."""
    if os.environ.get("EVENTRECON_MALLOC", "").strip().lower() == "default":
        return False
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):
        log.debug("no glibc mallopt: freed memory goes back to the system as usual")
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return (mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1
            and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1)
