"""The simulator benchmark's grating: its fast signal is the closed form it states."""

from __future__ import annotations

import numpy as np

from benchmarks.bench_sim import Grating


def test_the_grating_signal_equals_its_plain_expression_to_an_ulp() -> None:
    """``Grating.__call__`` (torch's vectorised sine in numpy's buffer) against the plain
    numpy expression of ``L = log(m(1 + c sin(a t + φ)) + ε)``, and position-independent:
    each sample's value is the same in any block, as the core's batching assumes."""
    gr = Grating(40, 30)
    rng = np.random.default_rng(0)
    g, t = rng.integers(0, gr.P, 5001), rng.random(5001)
    plain = np.log(gr.m * (1 + gr.c[g] * np.sin(gr.a[g] * t + gr.phi[g])) + gr.eps)
    fast = gr(g, t)
    assert fast.dtype == np.float64 and fast.shape == (5001,)
    assert np.abs(fast - plain).max() <= 4 * np.spacing(np.abs(plain).max())
    parts = np.concatenate([gr(g[a:a + 7], t[a:a + 7]) for a in range(0, 5001, 7)])
    np.testing.assert_array_equal(parts, fast)
