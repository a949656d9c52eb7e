"""eventrecon.allocator: freed blocks stay in the process (glibc), bounded by page faults."""

from __future__ import annotations

import platform
import resource

import numpy as np
import pytest

from eventrecon.allocator import retain_freed_memory

glibc = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's mallopt only")


def _faults() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def test_the_default_allocator_can_be_kept(monkeypatch):
    monkeypatch.setenv("EVENTRECON_MALLOC", "default")
    assert retain_freed_memory() is False


@glibc
def test_blocks_freed_and_allocated_again_fault_no_pages_in():
    # six 4 MiB arrays (6144 pages) allocated, written and freed ten times: glibc's default
    # trims the heap's free top (24 MiB > twice its dynamic threshold) and the next round
    # faults every page in again; with the thresholds fixed only the first round does
    assert retain_freed_memory() is True
    pages = 6 * (4 << 20) // 4096

    def round_trip() -> None:
        arrays = [np.ones(1 << 19) for _ in range(6)]     # 4 MiB of float64 each
        assert sum(float(a[-1]) for a in arrays) == 6.0

    round_trip()
    before = _faults()
    for _ in range(9):
        round_trip()
    assert _faults() - before < pages // 4            # nine rounds: < a quarter of one
