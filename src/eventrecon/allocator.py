"""Keep freed memory inside the process, so that loops stop faulting the same pages in.

glibc's ``malloc`` hands large freed blocks back to the kernel: a block above the mmap
threshold (128 KiB at first, raised on the fly up to 32 MiB) is unmapped when freed, and
the top of the heap is trimmed once more than the trim threshold (twice the mmap
threshold) lies free there. A loop that allocates and frees the same multi-MB arrays
then maps fresh pages on every pass and pays one page fault per 4 KiB page, zeroing
included (dear on a virtual machine). Two loops of eventrecon do exactly that:

- a render without gradients: each field call's encoding and activations (blocks of
  ``render.query_rows`` = 16 384 samples, several MB each) are freed before the next;
- the event core's iterations: the signal's temporaries and the time order's buffers.

:func:`retain_freed_memory` fixes both thresholds (``mallopt``; fixing the mmap threshold
also stops its adjustment): blocks up to :data:`MMAP_THRESHOLD` come from the heap, and
the heap is never trimmed. Measured on the 2-core AMX Xeon (docs/results/event_core.md,
"Buffers kept for the whole run"): the compiled event core on the 346×260 grating 4.5–9 %
faster at θ = 0.5 and 21–23 % at θ = 0.2; a 346×260 render of the 4×64 NeRF in a fresh
process 1.25–1.33 s instead of 1.99–2.10 s, but no faster after training in the same
process (glibc's own threshold has risen by then). The price is that the process keeps
its peak heap until it exits. Values are unchanged bit for bit: only where memory comes
from changes.

The command-line entry points call it (``train.py``, ``python -m eventrecon.evaluate``,
``python -m eventrecon.simulate``, ``python -m benchmarks``); a library user may call it
too. ``EVENTRECON_MALLOC=default`` keeps glibc's own behaviour. Elsewhere than glibc (macOS,
musl) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os

__all__ = ["MMAP_THRESHOLD", "TRIM_THRESHOLD", "retain_freed_memory"]

log = logging.getLogger(__name__)

#: Blocks up to this size come from the heap (glibc's own ceiling for the dynamic
#: threshold on 64-bit systems: 32 MiB).
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
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        log.debug("no glibc mallopt here: freed memory goes back to the system as usual")
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    ok = (mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1
          and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD) == 1)
    log.debug("malloc keeps freed blocks up to %d MiB: %s", MMAP_THRESHOLD >> 20, ok)
    return ok
