"""The ideal event core: analytic crossings, Σp·θ tracks the log signal, static → none."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eventrecon.sim.event_sim import simulate_events
from eventrecon.sim.ideal import CoreSettings, SignalSetup, crossings, run_core
from eventrecon.sim.pipeline import torch_threads
from eventrecon.sim.raytrace import PixelRenderer
from eventrecon.sim.spec import build_cameras, parse_spec


def tiny(name: str = "tiny", moving: bool = True, **over) -> dict:
    cfg = {
        "name": name, "seed": 3, "width": 24, "height": 18, "duration_s": 2.0,
        "rig": {"n_train": 1, "n_heldout": 1},
        "objects": [
            {"type": "sphere", "radius": 0.2, "position": [0, -0.3, 0],
             "texture": {"type": "checker", "colors": [[0.9, 0.2, 0.1], [0.2, 0.2, 0.9]],
                         "size": 0.1},
             "motion": [{"type": "orbit", "radius": 0.2, "turns": 1.0 if moving else 0.0},
                        {"type": "spin", "turns": 1.0 if moving else 0.0}]},
        ],
    }
    cfg.update(over)
    return cfg


def _setup(n: int, theta: float = 0.5) -> SignalSetup:
    return SignalSetup(np.full(n, theta), np.full(n, theta), np.full((n, 3), 1 / 3))


@pytest.mark.parametrize("slope", [3.7, -2.3, 0.49, 11.0])
def test_linear_ramp_gives_floor_dl_over_theta_events_at_analytic_times(slope):
    theta, P = 0.5, 5
    a = np.linspace(-1.0, 0.3, P)           # per-pixel start level
    sig = lambda g, t: a[g] + slope * t     # noqa: E731
    res = run_core(sig, np.arange(P), _setup(P, theta), CoreSettings(theta, 0.25, 0.01, 1e-7))
    n = int(np.floor(abs(slope) / theta))
    for g in range(P):
        t = res.t[res.g == g]
        assert t.size == n
        k = np.arange(1, n + 1)
        np.testing.assert_allclose(t, k * theta / abs(slope), rtol=0, atol=1e-9)
        assert np.all(res.p[res.g == g] == np.sign(slope))
    assert np.all(np.diff(res.t) >= 0)


def test_crossings_many_per_segment_and_both_polarities():
    ev, ref, _, _ = crossings(np.array([0, 1]), np.zeros(2), np.ones(2), np.array([0.0, 0.0]),
                              np.array([1.6, -1.1]), np.zeros(2), np.full(2, 0.5),
                              np.full(2, 0.5))
    t = np.concatenate([e[1] for e in ev])
    p = np.concatenate([e[2] for e in ev])
    g = np.concatenate([e[0] for e in ev])
    assert sorted(t[g == 0].tolist()) == pytest.approx([0.5 / 1.6, 1 / 1.6, 1.5 / 1.6])
    assert sorted(t[g == 1].tolist()) == pytest.approx([0.5 / 1.1, 1 / 1.1])
    assert set(p[g == 0]) == {1} and set(p[g == 1]) == {-1}
    np.testing.assert_allclose(ref, [1.5, -1.0])


def test_step_bound_is_respected_except_at_discontinuities():
    sig = lambda g, t: np.sin(20 * t + g) * 3.0  # noqa: E731  smooth, |dL/dt| ≤ 60
    res = run_core(sig, np.arange(4), _setup(4), CoreSettings(0.5, 0.2, 0.01, 1e-9),
                   record_samples=True)
    g, t, L = res.samples
    order = np.lexsort((t, g))
    g, t, L = g[order], t[order], L[order]
    same = g[1:] == g[:-1]
    assert np.abs(np.diff(L))[same].max() <= 0.2 * 0.5 + 1e-12
    assert res.n_forced == 0


def test_sum_of_polarities_tracks_rendered_log_intensity_within_theta():
    spec = parse_spec(tiny())
    cams, _ = build_cameras(spec)
    with torch_threads(1):
        streams, core = simulate_events(spec, PixelRenderer(spec.scene, cams),
                                        record_samples=True)
    assert core.t.size > 200
    g, t, L = core.samples
    theta = spec.threshold
    # reference level of each pixel = its first sample (t = 0)
    L0 = {}
    for gi, ti, Li in zip(g.tolist(), t.tolist(), L.tolist()):
        if ti == 0.0:
            L0[gi] = Li
    key_e = core.g * 2.0 + core.t
    order = np.argsort(key_e, kind="stable")
    cum = np.cumsum(core.p[order].astype(np.int64))
    key_sorted = key_e[order]
    idx = np.searchsorted(key_sorted, g * 2.0 + t, side="right") - 1
    start = np.searchsorted(key_sorted, g * 2.0, side="left") - 1
    total = np.where(idx >= 0, cum[np.maximum(idx, 0)], 0) - np.where(start >= 0,
                                                                     cum[np.maximum(start, 0)], 0)
    recon = np.array([L0[x] for x in g.tolist()]) + theta * total
    err = np.abs(recon - L)
    assert err.max() < theta
    assert len(t) > 10 * len(L0)


def test_static_scene_ideal_sensor_emits_no_events():
    spec = parse_spec(tiny(moving=False))
    cams, _ = build_cameras(spec)
    streams, core = simulate_events(spec, PixelRenderer(spec.scene, cams))
    assert sum(len(s) for s in streams) == 0 and core.n_samples == 0


def test_skipped_intervals_are_truly_constant():
    spec = parse_spec(tiny())
    cams, _ = build_cameras(spec)
    pr = PixelRenderer(spec.scene, cams)
    K = 50
    pix, busy = pr.activity(K)
    rng = np.random.default_rng(0)
    # every pixel, a random time in each of 5 random intervals: where not busy the
    # radiance equals the one at the interval start
    all_pix = np.arange(pr.n_pixels)
    busy_full = np.zeros((pr.n_pixels, K), bool)
    busy_full[pix] = busy
    for k in rng.choice(K, 5, replace=False):
        t0 = torch.full((pr.n_pixels,), k / K, dtype=torch.float64)
        t1 = torch.as_tensor(k / K + rng.random(pr.n_pixels) / K)
        a = pr.radiance(torch.as_tensor(all_pix), t0)
        b = pr.radiance(torch.as_tensor(all_pix), t1)
        quiet = ~busy_full[:, k]
        assert quiet.sum() > 0
        assert torch.equal(a[quiet], b[quiet])
    assert busy.any(1).all()
