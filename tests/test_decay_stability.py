"""Supplementary Sec. 15: accumulated noise diverges without decay and converges with it.

Closed forms (eventrecon.events.noise_theory) are checked against exact enumeration,
then against seeded Monte Carlo over many independent pixels with bounds of five
standard errors (the standard error of a sample variance estimated from the sample's
fourth central moment).
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from eventrecon.events.accumulate import DecayedEvents
from eventrecon.events.noise_theory import (
    eq15_supplementary,
    eq18_supplementary,
    noise_limits,
    noise_moments,
    simulate_noise_accumulation,
)
from eventrecon.events.stream import EventStream

P = 20000  # Monte-Carlo pixels


def mc_stats(x: torch.Tensor) -> tuple[float, float, float, float]:
    """(mean, var, 5·SE(mean), 5·SE(var)) of samples ``x [P]``."""
    x = x.double()
    n = x.numel()
    m = x.mean()
    c = x - m
    var = (c**2).mean()
    m4 = (c**4).mean()
    se_var = math.sqrt(max(float(m4 - var**2), 0.0) / n)
    return float(m), float(var), 5 * math.sqrt(float(var) / n), 5 * se_var


@pytest.mark.parametrize("qp,qm,b", [(0.5, 0.5, 1.0), (0.7, 0.2, 1.0), (0.6, 0.3, 0.93),
                                     (1.0, 0.0, 0.5)])
def test_closed_forms_equal_exact_enumeration(qp: float, qm: float, b: float) -> None:
    probs = {1: qp, -1: qm, 0: 1 - qp - qm}
    for n in range(1, 7):
        m1 = m2 = 0.0
        for seq in itertools.product((1, -1, 0), repeat=n):
            w = math.prod(probs[p] for p in seq)
            e = sum(p * b ** (n - 1 - i) for i, p in enumerate(seq))
            m1 += w * e
            m2 += w * e * e
        mom = noise_moments(n, qp, qm, b)
        assert float(mom.mean) == pytest.approx(m1, abs=1e-12)
        assert float(mom.second_moment) == pytest.approx(m2, abs=1e-12)
        assert float(mom.variance) == pytest.approx(m2 - m1**2, abs=1e-12)
        if b == 1.0:  # Eq. (15) as printed is E[E²] − E[E], not the variance
            assert float(eq15_supplementary(n, qp, qm)) == pytest.approx(m2 - m1, abs=1e-12)
        else:  # Eq. (18) as printed is the second moment
            assert float(eq18_supplementary(n, qp, qm, b)) == pytest.approx(m2, abs=1e-12)


def test_no_decay_balanced_noise_variance_grows_linearly() -> None:
    gen = torch.Generator().manual_seed(10)
    traj = simulate_noise_accumulation(400, P, 0.5, 0.5, 1.0, gen)
    for n in (25, 100, 400):
        mean, var, tol_m, tol_v = mc_stats(traj[n - 1])
        assert abs(mean) < tol_m                     # E[E_n] = 0
        assert abs(var - n) < tol_v                  # V(E_n) = n (Sec. 15: q± = ½)
    # Linear growth: var(400)/var(100) ≈ 4 (not 16).
    ratio = mc_stats(traj[399])[1] / mc_stats(traj[99])[1]
    assert abs(ratio - 4.0) < 0.25


def test_no_decay_biased_noise_second_moment_grows_quadratically() -> None:
    qp, qm = 0.6, 0.4
    gen = torch.Generator().manual_seed(11)
    traj = simulate_noise_accumulation(400, P, qp, qm, 1.0, gen)
    for n in (25, 100, 400):
        x = traj[n - 1]
        th = noise_moments(n, qp, qm)
        mean, var, tol_m, tol_v = mc_stats(x)
        assert abs(mean - n * 0.2) < tol_m                      # Eq. (14)
        assert abs(var - n * (1 - 0.04)) < tol_v                # linear: n·4q₊q₋
        m2 = float((x**2).mean())
        se_m2 = 5 * float((x**2).std()) / math.sqrt(P)
        assert abs(m2 - float(th.second_moment)) < se_m2        # n + n(n−1)·0.04
        # Eq. (15) as printed: n(n−1)(q₊−q₋)² + 2nq₋ = E[E²] − E[E].
        assert abs((m2 - mean) - float(eq15_supplementary(n, qp, qm))) < se_m2 + tol_m
    # Quadratic growth of the mean square deviation from the true level (0).
    r = float((traj[399] ** 2).mean() / (traj[99] ** 2).mean())
    assert r == pytest.approx(float(noise_moments(400, qp, qm).second_moment
                                     / noise_moments(100, qp, qm).second_moment), rel=0.03)
    assert r > 10.0


def test_eq15_is_not_the_variance() -> None:
    # q₊ = 1: E_n = n surely, so its variance is 0; Eq. (15) gives n² − n.
    traj = simulate_noise_accumulation(50, 100, 1.0, 0.0, 1.0, torch.Generator())
    assert float(traj[-1].var()) == 0.0 and float(traj[-1, 0]) == 50.0
    assert float(noise_moments(50, 1.0, 0.0).variance) == 0.0
    assert float(eq15_supplementary(50, 1.0, 0.0)) == 50 * 49


@pytest.mark.parametrize("qp,qm", [(0.5, 0.5), (0.6, 0.3), (0.9, 0.1)])
def test_decay_converges_to_closed_form_limits(qp: float, qm: float) -> None:
    b = 0.93
    gen = torch.Generator().manual_seed(12)
    traj = simulate_noise_accumulation(600, P, qp, qm, b, gen)
    lim_mean, lim_var = noise_limits(qp, qm, b)
    for n in (5, 20, 100):  # the finite-n closed forms
        th = noise_moments(n, qp, qm, b)
        mean, var, tol_m, tol_v = mc_stats(traj[n - 1])
        assert abs(mean - float(th.mean)) < tol_m and abs(var - float(th.variance)) < tol_v
    mean, var, tol_m, tol_v = mc_stats(traj[-1])  # b^600 ≈ 1e-19: at the limit
    assert abs(mean - lim_mean) < tol_m and abs(var - lim_var) < tol_v
    # Bounded: the spread never exceeds the limit (Var grows monotonically to it).
    spread = traj.var(1)
    assert float(spread.max()) < lim_var + 5 * tol_v
    assert float(spread[-100:].mean()) == pytest.approx(lim_var, rel=0.05)


def test_fig13_patch_decayed_events_bounded_naive_diverges() -> None:
    """DecayedEvents on a noisy constant patch: b = 1 spreads as √n, b = 0.93 stays bounded."""
    rng = np.random.default_rng(13)
    side, n_per_px, qp = 30, 600, 0.55  # 900 pixels, 600 noise events each
    n = side * side * n_per_px
    pix = np.repeat(np.arange(side * side), n_per_px)
    t = rng.uniform(0.0, 1000.0, n)
    p = np.where(rng.random(n) < qp, 1, -1).astype(np.int8)
    order = np.argsort(t, kind="stable")
    s = EventStream((pix % side)[order].astype(np.int16), (pix // side)[order].astype(np.int16),
                    t[order], p[order])
    all_pix = torch.arange(side * side)
    for b in (1.0, 0.93):
        ev = DecayedEvents.from_streams([s], side, side, b)
        v_end = ev.value(all_pix, 1000.0)
        th = noise_moments(n_per_px, qp, 1 - qp, b)
        mean, var, tol_m, tol_v = mc_stats(v_end)
        assert abs(mean - float(th.mean)) < tol_m and abs(var - float(th.variance)) < tol_v
        if b == 1.0:
            assert float(v_end.std()) > 0.9 * math.sqrt(n_per_px * (1 - 0.01))  # ≈ 24
        else:
            assert float(v_end.std()) < 1.1 * math.sqrt(noise_limits(qp, 1 - qp, b)[1])  # ≈ 2.7
