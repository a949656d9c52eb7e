"""Peak memory is per run: a big earlier job does not leak into the next job's figure."""

from __future__ import annotations

import mmap

import numpy as np
import pytest

from eventrecon.engine.memory import peak_mb, reset_peak


def test_peak_follows_an_allocation_and_resets() -> None:
    if not reset_peak():
        pytest.skip("the resident-set peak cannot be reset on this OS (not Linux)")
    base = peak_mb()
    # 200 MiB of fresh pages, touched: mapped directly, so that memory malloc keeps
    # (eventrecon.common.malloc, set by entry points run in this process) cannot serve it
    block = mmap.mmap(-1, 200 * 2**20)
    np.frombuffer(block, np.uint8)[::4096] = 1
    grown = peak_mb()
    block.close()
    assert grown - base > 190  # the 200 MiB block shows up
    assert reset_peak()
    assert peak_mb() < grown - 150  # and is forgotten after the reset
