"""Peak memory of one run, also when a sweep runs many jobs in one process.

``ru_maxrss`` only ever grows over a process's life, so with Hydra's default launcher
(jobs in turn, in one process) every job would report the largest job before it. A run
therefore calls :func:`reset_peak` first and :func:`peak_mb` last:

- GPU: ``torch.cuda`` peak allocated bytes (reset with ``reset_peak_memory_stats``);
- CPU on Linux: the resident-set high-water mark ``VmHWM`` of ``/proc/self/status``,
  reset by writing ``5`` to ``/proc/self/clear_refs`` (Linux ≥ 4.0);
- elsewhere: ``ru_maxrss`` (the process's peak; not resettable, said in the log).
"""

from __future__ import annotations

import logging
import resource
from pathlib import Path

import torch

__all__ = ["reset_peak", "peak_mb"]

log = logging.getLogger(__name__)
_STATUS = Path("/proc/self/status")
_CLEAR = Path("/proc/self/clear_refs")


def reset_peak(cuda: bool = False) -> bool:
    """Start a new peak (also of the current GPU's allocations with ``cuda``; without it
    no CUDA context is created); ``False`` if the CPU peak cannot be reset here."""
    if cuda and torch.cuda.is_available():
        torch.cuda.reset_peak_memory_stats()
    try:
        _CLEAR.write_text("5")
        return True
    except OSError:
        log.debug("cannot reset the resident-set peak (%s); peak memory is per process", _CLEAR)
        return False


def _vm_hwm_kb() -> int | None:
    try:
        for line in _STATUS.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


def peak_mb(cuda: bool = False) -> float:
    """Peak memory since :func:`reset_peak` in MiB: the GPU's allocations with ``cuda``,
    else the process's resident set."""
    if cuda and torch.cuda.is_available():
        return torch.cuda.max_memory_allocated() / 2**20
    kb = _vm_hwm_kb()
    if kb is None:
        kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kb / 1024.0
