"""Noise in the window sums the losses see, with and without event decay.

``window_noise_moments`` (closed form over Poisson counts) is checked against a seeded
Monte Carlo of the recurrence with bounds of five standard errors; ``window_stats`` on a
split of pure Poisson noise is checked against the closed form averaged over the same
windows.
"""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from eventrecon.common.errors import InputError
from eventrecon.data.sampling import sample_window
from eventrecon.data.types import SplitData
from eventrecon.data.window_stats import window_stats
from eventrecon.events.noise_theory import window_noise_moments
from eventrecon.events.stream import EventStream


def _mc_window_sums(lam0: float, lam1: float, qp: float, b: float, n: int,
                    rng: np.random.Generator) -> np.ndarray:
    """``E = V(t1) − V(t0)`` of ``n`` independent pixels by the recurrence itself."""
    n0, m = rng.poisson(lam0, n), rng.poisson(lam1, n)
    out = np.empty(n)
    for i in range(n):
        v = 0.0
        for p in np.where(rng.random(n0[i]) < qp, 1.0, -1.0):
            v = b * v + p
        v0 = v
        for p in np.where(rng.random(m[i]) < qp, 1.0, -1.0):
            v = b * v + p
        out[i] = v - v0
    return out


@pytest.mark.parametrize("lam0, lam1, qp, b", [
    (2.0, 1.0, 0.5, 0.93), (8.0, 6.0, 0.8, 0.93), (40.0, 10.0, 0.8, 0.93),
    (5.0, 3.0, 0.3, 0.5), (5.0, 3.0, 0.8, 1.0),
])
def test_window_moments_match_the_recurrence(lam0, lam1, qp, b):
    e = _mc_window_sums(lam0, lam1, qp, b, 20000, np.random.default_rng(1))
    mean, second = window_noise_moments(lam0, lam1, qp, 1 - qp, b)
    n = e.size
    assert abs(e.mean() - mean) < 5 * e.std() / math.sqrt(n)
    assert abs((e**2).mean() - second) < 5 * (e**2).std() / math.sqrt(n)


def test_without_decay_only_the_window_counts_and_with_decay_the_drift_vanishes():
    # b = 1: the history before t0 cancels exactly; mean μλ, second moment λ + μ²λ²
    for lam0 in (0.0, 5.0, 500.0):
        assert window_noise_moments(lam0, 4.0, 0.8, 0.2) == pytest.approx((2.4, 4 + 0.36 * 16))
    # b < 1 with a settled V (λ_before ≫ 1/(1 − b)): the window's drift is removed
    mean_settled, _ = window_noise_moments(1e4, 4.0, 0.8, 0.2, 0.93)
    assert abs(mean_settled) < 1e-9
    # ... but not from an empty history: then decay only shrinks the sum, μ·E[g_m(b)]
    mean_fresh, _ = window_noise_moments(0.0, 4.0, 0.8, 0.2, 0.93)
    assert mean_fresh == pytest.approx(0.6 * (1 - math.exp(-4.0 * 0.07)) / 0.07)
    assert 0.8 * 2.4 < mean_fresh < 2.4
    # balanced noise, few events: decay barely changes the mean square (the rig_noisy case)
    plain = window_noise_moments(1.8, 1.0, 0.5, 0.5)[1]
    decayed = window_noise_moments(1.8, 1.0, 0.5, 0.5, 0.93)[1]
    assert 0.9 * plain < decayed < plain


def test_window_moments_reject_bad_counts():
    with pytest.raises(InputError, match="lam_before"):
        window_noise_moments(-1.0, 1.0, 0.5, 0.5)


def _noise_split(rate: float, qp: float, views: int, h: int, w: int,
                 span: float, seed: int) -> SplitData:
    """Poisson noise only: ``rate`` events per pixel and time unit over ``[0, span]``."""
    rng = np.random.default_rng(seed)
    streams = []
    for _ in range(views):
        counts = rng.poisson(rate * span, h * w)
        pix = np.repeat(np.arange(h * w), counts)
        t = rng.random(pix.size) * span
        order = np.argsort(t, kind="stable")
        pix, t = pix[order], t[order]
        p = np.where(rng.random(pix.size) < qp, 1, -1).astype(np.int8)
        streams.append(EventStream((pix % w).astype(np.int16), (pix // w).astype(np.int16),
                                   t, p))
    return SplitData(root=Path("noise"), cameras=SimpleNamespace(height=h, width=w),
                     events=streams, frame_times=np.array([0.0, span]),
                     frames=np.zeros((2, views, h, w, 3), np.uint8))


def test_window_stats_on_pure_noise_match_the_closed_form():
    rate, qp, segment, b, n_win = 0.5, 0.8, (40.0, 100.0), 0.93, 40
    split = _noise_split(rate, qp, views=2, h=20, w=25, span=100.0, seed=3)
    st = window_stats(split, segment, b, windows=n_win, seed=7)
    assert st.subject is None and st.background.pixels == n_win * 2 * 20 * 25
    # the same windows, the closed form averaged over them
    gen = torch.Generator().manual_seed(7)
    moments = {1.0: [], b: []}
    for _ in range(n_win):
        a, c = sample_window(gen)
        t0 = segment[0] + a * (segment[1] - segment[0])
        t1 = segment[0] + c * (segment[1] - segment[0])
        for bb in moments:
            moments[bb].append(window_noise_moments(rate * t0, rate * (t1 - t0), qp, 1 - qp, bb))
    for bb, mean, rms in ((1.0, st.background.mean_plain, st.background.rms_plain),
                          (b, st.background.mean_decayed, st.background.rms_decayed)):
        want_mean = np.mean([m for m, _ in moments[bb]])
        want_rms = math.sqrt(np.mean([s for _, s in moments[bb]]))
        assert mean == pytest.approx(want_mean, abs=0.05 * want_rms), bb
        assert rms == pytest.approx(want_rms, rel=0.03), bb
    # decay removes most of the drift of ON-biased noise with a long history (λ_before ≥ 20)
    assert st.background.mean_decayed < 0.5 * st.background.mean_plain
    assert st.background.rms_change > 0


def test_window_stats_names_a_split_without_events():
    split = _noise_split(0.05, 0.5, 1, 4, 4, 100.0, 0)
    split.events = None
    with pytest.raises(InputError, match="events"):
        window_stats(split, (0.0, 100.0), 0.93)


def test_window_stats_names_a_bad_segment_or_window_count():
    split = _noise_split(0.05, 0.5, 1, 4, 4, 100.0, 0)
    with pytest.raises(InputError, match="segment"):
        window_stats(split, (50.0, 50.0), 0.93)
    with pytest.raises(InputError, match="windows"):
        window_stats(split, (0.0, 100.0), 0.93, windows=0)
