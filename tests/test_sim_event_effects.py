"""One test per event-side effect, each proving what the effect does with numbers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from eventrecon.common.errors import InputError
from eventrecon.sim.config import effect_rng
from eventrecon.sim.event_effects import (
    EVENT_EFFECTS,
    EventContext,
    ViewEvents,
    bayer_channel,
    first_order_lowpass,
)
from eventrecon.sim.event_sim import simulate_events
from eventrecon.sim.ideal import CoreSettings, SignalSetup, run_core
from eventrecon.sim.pipeline import torch_threads
from eventrecon.sim.raytrace import PixelRenderer
from eventrecon.sim.spec import build_cameras, parse_spec

CTX = EventContext(width=40, height=30, n_views=1, tonemap_eps=1e-2, threshold=0.5,
                   duration_s=2.0)


def build(*items):
    return EVENT_EFFECTS.build(list(items), "test")


def rng(i=0):
    return effect_rng(7, "events", "test", i)


def setup_for(effects, n, ctx=CTX):
    s = SignalSetup(np.full(n, ctx.threshold), np.full(n, ctx.threshold), np.full((n, 3), 1 / 3))
    for e in effects:
        e.configure(s, ctx, rng(e.index))
    return s


def ramp_events(setup, P, slope=20.0, settings=None):
    sig = lambda g, t: slope * t + 0.0 * g  # noqa: E731
    return run_core(sig, np.arange(P), setup, settings or CoreSettings(0.5, 0.25, 0.01, 1e-7))


def spacings(res):
    """Per-pixel log-level spacing of consecutive ON events on the slope-20 ramp."""
    order = np.lexsort((res.t, res.g))
    g, t = res.g[order], res.t[order]
    same = g[1:] == g[:-1]
    return g[1:][same], 20.0 * np.diff(t)[same]


def test_threshold_mismatch_std_sigma_and_frozen():
    fx = build({"name": "threshold_mismatch", "sigma": 0.03})
    s = setup_for(fx, 20000)
    assert s.theta_on.std() == pytest.approx(0.03, rel=0.05)
    assert s.theta_on.mean() == pytest.approx(0.5, abs=0.002)
    assert s.theta_off.std() == pytest.approx(0.03, rel=0.05)
    # frozen: every crossing of a pixel uses the same threshold, over the whole sequence
    res = ramp_events(s, 300)
    g, dl = spacings(res)
    np.testing.assert_allclose(dl, s.theta_on[g], atol=1e-9)
    # same seed, same thresholds
    np.testing.assert_array_equal(setup_for(fx, 20000).theta_on, s.theta_on)


def test_threshold_noise_redrawn_per_event_with_std_sigma():
    fx = build({"name": "threshold_noise", "sigma": 0.05})
    res = ramp_events(setup_for(fx, 400), 400)
    _, dl = spacings(res)
    assert dl.size > 5000
    assert dl.std() == pytest.approx(0.05, rel=0.05)
    assert dl.mean() == pytest.approx(0.5, abs=0.005)


def test_bandwidth_delays_a_step_by_tau_ln2_and_dim_is_slower():
    def first_event_delay(level):
        ctx = EventContext(1, 1, 1, 1e-2, 0.5, duration_s=1.0)
        fx = build({"name": "bandwidth", "cutoff_hz": 2.0})
        s = setup_for(fx, 1, ctx)
        L0 = math.log(level + 1e-2)
        sig = lambda g, t: L0 + 1.0 * (t >= 0.25)  # noqa: E731  step of 2θ at t = 0.25
        res = run_core(sig, np.array([0]), s, CoreSettings(0.5, 0.05, 2e-3, 1e-9))
        I1 = math.exp(L0 + 1.0) - 1e-2
        tau = 1 / (2 * math.pi * 2.0 * I1)
        return res.t[0] - 0.25, tau
    d_bright, tau_b = first_event_delay(0.3)
    d_dim, tau_d = first_event_delay(0.1)
    assert d_bright == pytest.approx(tau_b * math.log(2), rel=0.01)
    assert d_dim == pytest.approx(tau_d * math.log(2), rel=0.01)
    # the cutoff is proportional to intensity: the dim step lags ~2.7x longer
    assert tau_d / tau_b == pytest.approx((0.31 * math.e - 0.01) / (0.11 * math.e - 0.01))
    assert d_dim / d_bright == pytest.approx(tau_d / tau_b, rel=0.02) and d_dim > 2.5 * d_bright


def test_first_order_lowpass_exact_for_linear_input():
    # one big step equals many small steps (first-order hold is exact for linear input)
    ua, ub, tau = 0.0, 1.0, 0.3
    one = first_order_lowpass(np.array([0.2]), np.array([ua]), np.array([ub]),
                              np.array([tau]), np.array([1.0]))
    y = np.array([0.2])
    for k in range(1000):
        y = first_order_lowpass(y, np.array([k / 1000]), np.array([(k + 1) / 1000]),
                                np.array([tau]), np.array([1e-3]))
    np.testing.assert_allclose(one, y, rtol=1e-12)


def test_bayer_pixels_see_only_their_channel():
    assert bayer_channel(np.array([0, 0, 1, 1]), np.array([0, 1, 0, 1])).tolist() == [0, 1, 1, 2]
    s = setup_for(build({"name": "bayer"}), CTX.n_pixels)
    w = s.channel_weights.reshape(30, 40, 3)
    assert w[0, 0].tolist() == [1, 0, 0] and w[0, 1].tolist() == [0, 1, 0]
    assert w[1, 0].tolist() == [0, 1, 0] and w[1, 1].tolist() == [0, 0, 1]
    # end to end: a pure red sphere moving on black: only R pixels fire
    cfg = {"name": "red", "width": 24, "height": 18, "background": [0, 0, 0],
           "rig": {"n_train": 1, "n_heldout": 0},
           "objects": [{"type": "sphere", "radius": 0.2, "position": [0, -0.3, 0],
                        "texture": {"type": "solid", "color": [1, 0, 0]},
                        "motion": {"type": "orbit", "radius": 0.2}}],
           "events": [{"name": "bayer"}]}
    spec = parse_spec(cfg)
    cams, _ = build_cameras(spec)
    with torch_threads(1):
        (ev,), _ = simulate_events(spec, PixelRenderer(spec.scene, cams))
    assert len(ev) > 100
    assert np.all(bayer_channel(ev.y, ev.x) == 0)


def _empty():
    return ViewEvents(np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int8))


def test_shot_noise_rate():
    (fx,) = build({"name": "shot_noise", "rate_hz": 5.0})
    ev = fx.apply(_empty(), CTX, rng())
    rate = ev.t.size / (CTX.n_pixels * CTX.duration_s)
    assert rate == pytest.approx(5.0, rel=0.05)
    assert np.mean(ev.p == 1) == pytest.approx(0.5, abs=0.02)
    assert np.all(np.diff(ev.t) >= 0)


def test_leak_periodic_on_events_at_rate():
    (fx,) = build({"name": "leak", "rate_hz": 3.0})
    ev = fx.apply(_empty(), CTX, rng())
    assert np.all(ev.p == 1)
    assert ev.t.size / (CTX.n_pixels * CTX.duration_s) == pytest.approx(3.0, rel=0.02)
    order = np.lexsort((ev.t, ev.pix))
    same = ev.pix[order][1:] == ev.pix[order][:-1]
    gaps = np.diff(ev.t[order])[same] / 1000 * CTX.duration_s
    np.testing.assert_allclose(gaps, 1 / 3.0, atol=1e-9)


def test_refractory_gap_and_matches_greedy_reference():
    (fx,) = build({"name": "refractory", "period_s": 0.01})
    r = np.random.default_rng(1)
    n = 3000
    ev = ViewEvents(r.integers(0, 20, n), np.sort(r.uniform(0, 1000, n)),
                    np.ones(n, np.int8))
    out = fx.apply(ev, CTX, rng())
    period = 0.01 * 1000 / CTX.duration_s
    for px in range(20):
        t = out.t[out.pix == px]
        assert np.all(np.diff(t) >= period - 1e-6)
        ref, last = [], -np.inf                          # slow greedy reference
        for ti in ev.t[ev.pix == px]:
            if ti - last >= period:
                ref.append(ti)
                last = ti
        np.testing.assert_array_equal(t, ref)
    assert out.t.size < n


def test_timestamp_jitter_std():
    (fx,) = build({"name": "timestamp_jitter", "sigma_s": 1e-3})
    n = CTX.n_pixels
    ev = ViewEvents(np.arange(n), np.full(n, 500.0), np.ones(n, np.int8))
    out = fx.apply(ev, CTX, rng())
    d = out.t[np.argsort(out.pix)] - 500.0
    assert d.std() == pytest.approx(1e-3 * 1000 / CTX.duration_s, rel=0.05)
    assert np.all(np.diff(out.t) >= 0)


def test_hot_pixels_count_and_rate():
    (fx,) = build({"name": "hot_pixels", "fraction": 0.01, "rate_hz": 200.0})
    ev = fx.apply(_empty(), CTX, rng())
    hot = np.unique(ev.pix)
    assert hot.size == round(0.01 * CTX.n_pixels)
    assert ev.t.size / (hot.size * CTX.duration_s) == pytest.approx(200.0, rel=0.05)


def test_unlisted_effects_draw_nothing_and_do_not_perturb_others():
    a = build({"name": "shot_noise", "rate_hz": 2.0})
    b = build({"name": "leak", "rate_hz": 0.0}, {"name": "shot_noise", "rate_hz": 2.0},
              {"name": "hot_pixels", "fraction": 0.0, "rate_hz": 1.0})
    def run(fx):
        ev = _empty()
        for e in fx:
            ev = e.apply(ev, CTX, effect_rng(7, "events", e.name, e.occurrence, 0))
        return ev
    ea, eb = run(a), run(b)
    np.testing.assert_array_equal(ea.t, eb.t)
    np.testing.assert_array_equal(ea.pix, eb.pix)


def test_effect_config_errors():
    with pytest.raises(InputError, match=r"events\[0\].name: expected one of bandwidth, bayer"):
        build({"name": "shotnoise"})
    with pytest.raises(InputError, match=r"events\[0\].rate_hz"):
        build({"name": "shot_noise", "rate_hz": -1.0})
    with pytest.raises(InputError, match=r"events\[0\].sigma"):
        build({"name": "threshold_mismatch", "sigma": -0.1})
    with pytest.raises(InputError, match=r"events\[0\].rate: expected a parameter of shot_noise"):
        build({"name": "shot_noise", "rate": 1.0})
    with pytest.raises(InputError, match=r"events\[1\].name: expected threshold_mismatch"):
        build({"name": "refractory", "period_s": 1e-3}, {"name": "threshold_mismatch",
                                                          "sigma": 0.03})
    with pytest.raises(InputError, match="threshold: expected a contrast threshold > 0"):
        parse_spec({"name": "x", "threshold": 0.0})
