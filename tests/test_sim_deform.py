"""The deforming `skirt` primitive: exact intersection against a slow independent
reference (dense marching + bisection on the implicit function), normals, material
points, bounds, and its config errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from eventrecon.common.errors import InputError
from eventrecon.sim.scene import parse_scene
from eventrecon.sim.skirt import intersect_skirt, parse_skirt

CFG = {"rings": [[-0.3, 0.1], [-0.2, 0.12], [-0.1, 0.08], [0.05, 0.2], [0.2, 0.28], [0.3, 0.3]],
       "sway": {"amplitude": 0.05, "turns": 1.3, "lag_deg": 70, "phase_deg": 20},
       "flare": {"amplitude": 0.25, "cycles": 2.0},
       "squash": {"amplitude": 0.15, "turns": -0.7}}


def reference_rings(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(c [n, 2], s [n], E [2, 2])`` straight from the formulas of the module docstring."""
    y, r = np.array(CFG["rings"]).T
    v = (y - y[0]) / (y[-1] - y[0])
    sw, fl, sq = CFG["sway"], CFG["flare"], CFG["squash"]
    psi = math.radians(sw["phase_deg"]) + 2 * math.pi * sw["turns"] * t \
        - math.radians(sw["lag_deg"]) * v
    c = sw["amplitude"] * v[:, None] ** 2 * np.stack([np.sin(psi), np.cos(psi)], -1)
    s = r * (1 + fl["amplitude"] * v * (1 - math.cos(2 * math.pi * fl["cycles"] * t)) / 2)
    b = 2 * math.pi * sq["turns"] * t
    Q = np.array([[math.cos(b), -math.sin(b)], [math.sin(b), math.cos(b)]])
    E = Q @ np.diag([1 + sq["amplitude"], 1 - sq["amplitude"]]) @ Q.T
    return c, s, E


def reference_f(x: np.ndarray, t: float) -> np.ndarray:
    """``|E⁻¹(q − c(λ))| − s(λ)`` at points ``x [..., 3]`` (NaN outside the rings' heights)."""
    y = np.array(CFG["rings"])[:, 0]
    c, s, E = reference_rings(t)
    j = np.clip(np.searchsorted(y, x[..., 1], side="right") - 1, 0, len(y) - 2)
    lam = (x[..., 1] - y[j]) / (y[j + 1] - y[j])
    cl = c[j] + lam[..., None] * (c[j + 1] - c[j])
    sl = s[j] + lam * (s[j + 1] - s[j])
    m = np.linalg.solve(E, (x[..., [0, 2]] - cl)[..., None])[..., 0]
    out = np.linalg.norm(m, axis=-1) - sl
    return np.where((x[..., 1] >= y[0]) & (x[..., 1] <= y[-1]), out, np.nan)


def _rays(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays from outside (aimed at the skirt's region) and from inside it, random times."""
    rng = np.random.default_rng(seed)
    n_in = n // 5
    u = rng.normal(size=(n - n_in, 3))
    o_out = 2.5 * u / np.linalg.norm(u, axis=1, keepdims=True)
    aim = np.stack([rng.uniform(-0.35, 0.35, n - n_in), rng.uniform(-0.32, 0.32, n - n_in),
                    rng.uniform(-0.35, 0.35, n - n_in)], -1)
    o_in = np.stack([rng.uniform(-0.05, 0.05, n_in), rng.uniform(-0.25, 0.25, n_in),
                     rng.uniform(-0.05, 0.05, n_in)], -1)
    o = np.concatenate([o_out, o_in])
    d = np.concatenate([aim - o_out, rng.normal(size=(n_in, 3))])
    return o, d / np.linalg.norm(d, axis=1, keepdims=True), rng.uniform(0, 1, n)


def test_exact_intersection_matches_dense_marching_reference():
    """Against 30 000 samples per ray plus bisection (an independent implementation of
    the implicit surface): every clear hit agrees to 1e-9, every clear miss is a miss;
    only rays within 1e-6 of tangency (a double root the sampling can miss) are skipped."""
    sk = parse_skirt(CFG, "test", "")
    o, d, t = _rays(160, 0)
    tau, _, _ = intersect_skirt(*(torch.as_tensor(a) for a in (o, d, t)), sk)
    tau = tau.numpy()
    steps = np.linspace(0.0, 5.0, 30001)
    checked = hits = 0
    for i in range(len(o)):
        f = reference_f(o[i] + steps[:, None] * d[i], t[i])
        ok = np.isfinite(f[:-1]) & np.isfinite(f[1:])
        cross = np.nonzero(ok & (np.sign(f[:-1]) != np.sign(f[1:])) & (steps[1:] > 1e-9))[0]
        near = np.nanmin(np.abs(f)) if np.isfinite(f).any() else np.inf
        if not cross.size:
            if near > 1e-6:
                assert math.isinf(tau[i]), (i, tau[i], near)
                checked += 1
            continue
        a, b = steps[cross[0]], steps[cross[0] + 1]
        fa = f[cross[0]]
        for _ in range(80):
            m = 0.5 * (a + b)
            fm = reference_f(o[i] + m * d[i], t[i])
            a, b, fa = (m, b, fm) if np.sign(fm) == np.sign(fa) else (a, m, fa)
        # a tangent touch before the first sign change would be a grazing double root
        before = np.abs(f[:cross[0]][np.isfinite(f[:cross[0]])])
        if before.size and before.min() <= 1e-6:
            continue
        assert tau[i] == pytest.approx(0.5 * (a + b), abs=1e-9), i
        checked += 1
        hits += 1
    assert checked >= 0.95 * len(o) and hits >= 0.5 * len(o)


def test_hit_point_normal_and_material_point():
    """The hit lies on the surface (|f| ≤ 1e-12), its normal is the implicit gradient
    (finite differences) turned to the viewer, and the material point (the texture
    coordinate) maps back through the deformation to the hit point."""
    sk = parse_skirt(CFG, "test", "")
    o, d, t = _rays(400, 1)
    tau, n, p = (x.numpy() for x in intersect_skirt(*(torch.as_tensor(a) for a in (o, d, t)), sk))
    hit = np.isfinite(tau)
    assert hit.sum() > 200
    y, r_rest = np.array(CFG["rings"]).T
    for i in np.nonzero(hit)[0][:150]:
        x = o[i] + tau[i] * d[i]
        assert abs(reference_f(x, t[i])) < 1e-12
        h = 1e-6
        g = np.array([(reference_f(x + h * e, t[i]) - reference_f(x - h * e, t[i])) / (2 * h)
                      for e in np.eye(3)])
        g /= np.linalg.norm(g)
        assert abs(abs(g @ n[i]) - 1) < 1e-6 and n[i] @ d[i] <= 0
        # material point (r(λ) sin α, y, r(λ) cos α) → deformed ring point c(λ) + s(λ)E u(α)
        alpha = math.atan2(p[i, 0], p[i, 2])
        j = min(np.searchsorted(y, p[i, 1], side="right") - 1, len(y) - 2)
        lam = (p[i, 1] - y[j]) / (y[j + 1] - y[j])
        assert math.hypot(p[i, 0], p[i, 2]) == pytest.approx(
            r_rest[j] + lam * (r_rest[j + 1] - r_rest[j]), abs=1e-12)
        c, s, E = reference_rings(t[i])
        q = c[j] + lam * (c[j + 1] - c[j]) + (s[j] + lam * (s[j + 1] - s[j])) * (
            E @ np.array([math.sin(alpha), math.cos(alpha)]))
        np.testing.assert_allclose(q, x[[0, 2]], atol=1e-12)


def _surface(t: float, n_alpha: int = 90, n_lam: int = 7) -> np.ndarray:
    """Surface points ``[P, 3]`` of the reference skirt at time ``t``."""
    y = np.array(CFG["rings"])[:, 0]
    c, s, E = reference_rings(t)
    a = np.linspace(0, 2 * math.pi, n_alpha, endpoint=False)
    u = np.stack([np.sin(a), np.cos(a)], -1) @ E.T
    pts = []
    for j in range(len(y) - 1):
        for lam in np.linspace(0, 1, n_lam):
            q = c[j] + lam * (c[j + 1] - c[j]) + (s[j] + lam * (s[j + 1] - s[j])) * u
            pts.append(np.stack([q[:, 0], np.full(n_alpha, y[j] + lam * (y[j + 1] - y[j])),
                                 q[:, 1]], -1))
    return np.concatenate(pts)


def test_bounds_hold_the_deforming_sheet():
    """The bounding radius, the band/sector spheres (activity culling) and the ring
    points (cylinder check) contain the sheet at 60 times; the sheet is non-rigid
    (distances between material points change)."""
    sk = parse_skirt(CFG, "test", "")
    centres, radii = sk.band_spheres()
    t_all = np.linspace(0, 1, 30)
    dist = []
    for t in t_all:
        pts = _surface(t)
        assert np.linalg.norm(pts, axis=1).max() <= sk.bound_radius() + 1e-12
        inside = np.linalg.norm(pts[:, None] - centres[None], axis=-1) <= radii[None] + 1e-12
        assert inside.any(1).all()
        rp, margin = sk.ring_points(torch.tensor([t], dtype=torch.float64))
        rho = np.hypot(rp[0, :, 0].numpy(), rp[0, :, 2].numpy()).max() + margin
        assert np.hypot(pts[:, 0], pts[:, 2]).max() <= rho
        dist.append(np.linalg.norm(pts[5] - pts[-40]))
    assert np.ptp(dist) > 0.01   # not a rigid motion


def test_renderer_shades_the_skirt_and_moves_its_texture():
    """Through the scene renderer: a ray through the skirt sees its texture at the
    material point; spinning the skirt moves the stripes past a fixed ray."""
    cfg = {"objects": [{"type": "skirt", "position": [0, 0, 0], **CFG,
                        "texture": {"type": "stripes", "colors": [[1, 1, 1], [0, 0, 0]],
                                    "period": 0.05, "axis": [1, 0, 0]},
                        "motion": {"type": "spin", "axis": [0, 1, 0], "turns": 1.0}}],
           "light": {"ambient": 1.0, "intensity": 0.0}, "background": [0.5, 0.5, 0.5]}
    from eventrecon.sim.raytrace import Renderer

    r = Renderer(parse_scene(cfg, "test"))
    ts = torch.linspace(0, 0.2, 41, dtype=torch.float64)
    o = torch.tensor([[0.02, 0.1, -3.0]], dtype=torch.float64).repeat(41, 1)
    d = torch.tensor([[0, 0, 1.0]], dtype=torch.float64).repeat(41, 1)
    rgb = r.radiance(o, d, ts)
    assert set(np.unique(rgb[:, 0].numpy()).tolist()) == {0.0, 1.0}   # both stripes pass by


def test_skirt_config_errors_name_the_field():
    bad_rings = {"type": "skirt", "rings": [[0.1, 0.2], [0.0, 0.3]]}
    with pytest.raises(InputError, match=r"objects\[0\]\.rings: expected at least two"):
        parse_scene({"objects": [bad_rings]}, "scene x")
    with pytest.raises(InputError, match=r"objects\[0\]\.squash\.amplitude: expected an "
                                         r"amplitude in \[0, 1\)"):
        parse_scene({"objects": [{"type": "skirt", "rings": [[0, 0.1], [0.1, 0.2]],
                                  "squash": {"amplitude": 1.0}}]}, "scene x")
    with pytest.raises(InputError, match=r"objects\[0\]\.sway\.turns: expected a number"):
        parse_scene({"objects": [{"type": "skirt", "rings": [[0, 0.1], [0.1, 0.2]],
                                  "sway": {"turns": "two"}}]}, "scene x")
