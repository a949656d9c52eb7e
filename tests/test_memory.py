"""Peak memory is per run: a big earlier job does not leak into the next job's figure."""

from __future__ import annotations

import numpy as np
import pytest

from eventrecon.engine.memory import peak_mb, reset_peak


def test_peak_follows_an_allocation_and_resets() -> None:
    if not reset_peak():
        pytest.skip("the resident-set peak cannot be reset on this OS (not Linux)")
    base = peak_mb()
    block = np.ones(200 * 2**20 // 8)  # 200 MiB, touched
    block += 1
    grown = peak_mb()
    del block
    assert grown - base > 190  # the 200 MiB block shows up
    assert reset_peak()
    assert peak_mb() < grown - 150  # and is forgotten after the reset
