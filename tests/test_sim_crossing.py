"""The event core's crossing times (:mod:`eventrecon.sim.crossing`): exact on polynomials
of the interpolant's degree, the first root on a leg."""

from __future__ import annotations

import numpy as np
from test_sim_turns import SmallGrating, _setup

from eventrecon.sim import crossing
from eventrecon.sim.crossing import cross_times, first_root, newton_form, poly
from eventrecon.sim.ideal import CoreSettings, run_core


def _legs(Pt: np.ndarray, PL: np.ndarray, length: np.ndarray, frac: float = 0.37):
    """Every leg ``c → c+1`` with ``1 ≤ c ≤ length − 2`` of each column, and a level a
    fraction ``frac`` of the way along it: ``(c, i, level)``."""
    c, i = [], []
    for col, n in enumerate(length):
        c += list(range(1, n - 1))
        i += [col] * (n - 2)
    c, i = np.array(c), np.array(i)
    return c, i, PL[c, i] + frac * (PL[c + 1, i] - PL[c, i])


def _true_root(f, lo, hi, level):
    """``f(t) = level`` on ``[lo, hi]`` (``f`` increasing there), 80 bisections."""
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        below = f(mid) < level
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return 0.5 * (lo + hi)


def _normalised(f, Pt, PL, c, i, s):
    """``ℓ(s) = (f(t_c + s·h) − L_c)/(L_{c+1} − L_c)`` on the legs ``c → c+1`` of columns
    ``i`` (``s [K, 1]``): the exact curve the Newton form interpolates."""
    x1, h, y1 = Pt[c, i], Pt[c + 1, i] - Pt[c, i], PL[c, i]
    return (f(x1 + s * h) - y1) / (PL[c + 1, i] - y1)


def test_the_crossing_polynomial_is_the_quintic_through_two_neighbours_a_side():
    rng = np.random.default_rng(1)
    f = lambda t: t + 0.3 * t ** 2 - 0.2 * t ** 3 + 0.05 * t ** 4 + 0.02 * t ** 5  # noqa: E731
    Pt = np.sort(rng.uniform(0.0, 2.0, (9, 40)), axis=0)      # uneven steps, 40 paths
    PL, length = f(Pt), np.full(40, 9)
    c, i, _ = _legs(Pt, PL, length)
    inner = (c >= 2) & (c <= 5)                               # nodes c−2 … c+3 all there
    *_, C, Z = newton_form(Pt, PL, c, i, length)
    s = np.linspace(-0.5, 1.5, 21)[:, None]
    err = np.abs(poly(s, C, Z)[0] - _normalised(f, Pt, PL, c, i, s))
    assert err[:, inner].max() <= 1e-8
    assert err[:, ~inner].max() > 1e-4                        # fewer nodes: not exact


def test_the_crossing_polynomial_is_exact_for_a_cubic_on_every_leg_with_four_nodes():
    f = lambda t: 2 * t + 0.5 * t ** 2 + 0.3 * t ** 3                       # noqa: E731
    Pt = np.array([[0.0], [0.3], [0.5], [1.1], [1.4], [2.0]])
    PL = f(Pt)
    s = np.linspace(0.0, 1.0, 11)[:, None]
    for n in (4, 5, 6):                                     # paths ending early
        length = np.array([n])
        c, i, _ = _legs(Pt, PL, length)
        *_, C, Z = newton_form(Pt, PL, c, i, length)
        np.testing.assert_allclose(poly(s, C, Z)[0], _normalised(f, Pt, PL, c, i, s),
                                   rtol=0, atol=1e-12)


def test_gently_curved_legs_are_timed_to_1e_10_of_a_leg():
    # a leg of a sensor's path: its slope changes by a few % (the core's curvature bound)
    f = lambda t: t + 0.02 * t ** 2 + 0.004 * t ** 3 - 0.001 * t ** 5       # noqa: E731
    Pt = np.linspace(0.0, 1.6, 9)[:, None] + np.zeros((1, 5))
    PL, length = f(Pt), np.full(5, 9)
    for frac in (0.05, 0.37, 0.93):
        c, i, level = _legs(Pt, PL, length, frac)
        t = cross_times(Pt, PL, c, i, level, length)
        truth = _true_root(f, Pt[c, i], Pt[c + 1, i], level)
        inner = (c >= 2) & (c <= 5)                           # the quintic's legs
        np.testing.assert_allclose(t[inner], truth[inner], rtol=0, atol=2e-11)
        assert np.abs(t - truth).max() <= 1e-5                # quartic / cubic at the ends


def _random_paths(seed: int, n: int = 3000, C: int = 9):
    """Random walks with repeated points at the start (as a fresh pixel's state), short
    paths and legs of every curvature, and a level inside each chosen leg."""
    rng = np.random.default_rng(seed)
    Pt = np.cumsum(rng.exponential(1.0, (C, n)), 0)
    Pt[:2, : n // 3] = Pt[2, : n // 3]                        # s_{−2} = s_{−1} = s_0
    PL = np.cumsum(rng.normal(0.0, 1.0, (C, n)), 0)
    length = rng.integers(4, C + 1, n)
    c = np.minimum(rng.integers(1, C - 1, n), length - 2)
    i = np.arange(n)
    frac = rng.uniform(0.01, 1.0, n)
    return Pt, PL, length, c, i, PL[c, i] + frac * (PL[c + 1, i] - PL[c, i])


def test_the_time_is_the_first_root_on_the_leg(monkeypatch):
    # the crossings of the core's own paths on the small grating (the default settings),
    # against a dense scan for the first sign change of ℓ(s) − u
    seen = []

    def recorded(u, C, Z):
        s = first_root(u, C, Z)
        seen.append((u, C, Z, s))
        return s
    monkeypatch.setattr(crossing, "first_root", recorded)
    gr = SmallGrating()
    P = gr.W * gr.H
    run_core(gr, np.arange(P), _setup(P, 0.5), CoreSettings(0.5))
    u, s = (np.concatenate([x[k] for x in seen]) for k in (0, 3))
    C, Z = (np.concatenate([x[k] for x in seen], 1) for k in (1, 2))
    grid = np.linspace(0.0, 1.0, 4097)[:, None]
    first = grid[np.argmax(poly(grid, C, Z)[0] - u >= 0, axis=0), 0]
    wiggly = np.any(np.diff(np.sign(poly(grid, C, Z)[1]), axis=0) != 0, axis=0)
    assert u.size > 6000 and wiggly.sum() >= 5                # non-monotone legs, too
    resid = np.abs(poly(s, C, Z)[0] - u)                      # a root (Newton's error
    assert np.median(resid) <= 1e-8 and resid.max() <= 1e-4  # after a short step) ...
    assert np.all(np.abs(s - first) <= 1 / 4096 + 1e-4)       # ... and the first one
