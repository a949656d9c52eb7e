"""Exact ray-primitive intersections, shading, motions and textures against known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from eventrecon.errors import InputError
from eventrecon.sim.motion import parse_motions, rotation_matrices
from eventrecon.sim.raytrace import Renderer, intersect_box, intersect_plane, intersect_sphere
from eventrecon.sim.scene import parse_scene

f64 = dict(dtype=torch.float64)


def _unit(v):
    v = torch.tensor(v, **f64)
    return v / v.norm(dim=-1, keepdim=True)


def test_sphere_hits_misses_tangent_and_inside():
    o = torch.tensor([[0, 0, -3.0], [0.6, 0, -3.0], [2.0, 0, -3.0], [0, 0, 0.0]], **f64)
    d = torch.tensor([[0, 0, 1.0]] * 4, **f64)
    s = intersect_sphere(o, d, 1.0)
    assert s[0].item() == pytest.approx(2.0, abs=1e-15)
    assert s[1].item() == pytest.approx(3.0 - math.sqrt(1 - 0.36), abs=1e-14)
    assert math.isinf(s[2].item())
    assert s[3].item() == pytest.approx(1.0)          # from inside: the far root
    # an oblique ray: the hit point lies on the sphere
    oo, dd = torch.tensor([[1.0, 2.0, -4.0]], **f64), _unit([[-0.2, -0.45, 1.0]])
    p = oo + intersect_sphere(oo, dd, 0.7)[:, None] * dd
    assert p.norm().item() == pytest.approx(0.7, abs=1e-13)


def test_box_axis_aligned_and_rotated():
    o = torch.tensor([[0, 0, -3.0], [0.5, 0.2, -3.0], [3.0, 0, -3.0]], **f64)
    d = torch.tensor([[0, 0, 1.0]] * 3, **f64)
    s, n = intersect_box(o, d, torch.tensor([1.0, 1.0, 0.5], **f64))
    assert s[:2].tolist() == [2.5, 2.5] and math.isinf(s[2].item())
    assert n[0].tolist() == [0, 0, -1]
    # a unit cube turned 45° about y, seen along z: the edge is at distance √2·0.5
    R = rotation_matrices(torch.tensor([0, 1.0, 0], **f64),
                          torch.tensor([math.pi / 4], **f64))[0]
    ol, dl = (o[:1] @ R), (d[:1] @ R)
    s2, n2 = intersect_box(ol, dl, torch.tensor([0.5, 0.5, 0.5], **f64))
    assert s2.item() == pytest.approx(3 - math.sqrt(0.5), abs=1e-14)
    assert abs(n2[0]).sum().item() == pytest.approx(1.0)


def test_plane():
    o = torch.tensor([[0, -1.0, 0], [0, -1.0, 0]], **f64)
    d = _unit([[0, 1.0, 1.0], [0, -1.0, 0]])
    s = intersect_plane(o, d, 0.3)
    assert s[0].item() == pytest.approx(1.3 * math.sqrt(2), abs=1e-14) and math.isinf(s[1])


def test_lambertian_shading_of_a_sphere_and_background():
    cfg = {"objects": [{"type": "sphere", "radius": 0.5, "position": [0, 0, 0],
                        "texture": {"type": "solid", "color": [0.8, 0.4, 0.2]}}],
           "light": {"direction": [0, 0, -1], "ambient": 0.1, "intensity": 0.6},
           "background": [0.3, 0.3, 0.3]}
    r = Renderer(parse_scene(cfg, "test"))
    o = torch.tensor([[0, 0, -3.0], [0.3, 0, -3.0], [2, 2, -3.0]], **f64)
    d = torch.tensor([[0, 0, 1.0]] * 3, **f64)
    rgb = r.radiance(o, d, torch.zeros(3, **f64))
    alb = torch.tensor([0.8, 0.4, 0.2], **f64)
    torch.testing.assert_close(rgb[0], alb * (0.1 + 0.6), rtol=0, atol=1e-14)
    cos = math.sqrt(1 - 0.36)               # normal of the hit at x = 0.3 on r = 0.5
    torch.testing.assert_close(rgb[1], alb * (0.1 + 0.6 * cos), rtol=0, atol=1e-12)
    torch.testing.assert_close(rgb[2], torch.full((3,), 0.3, **f64))


def test_motions_known_values():
    ms = parse_motions([{"type": "orbit", "radius": 0.2, "turns": 1.0},
                        {"type": "bounce", "height": 0.5, "bounces": 2},
                        {"type": "linear", "to": [1, 0, 0]},
                        {"type": "keyframe", "keys": [[0, 0, 0, 0], [0.5, 0, 0, 1], [1, 0, 0, 0]]}],
                       "test", "motion")
    t = torch.tensor([0.0, 0.25, 0.375], **f64)
    torch.testing.assert_close(ms[0].displacement(t)[1], torch.tensor([0.2, 0, 0], **f64))
    torch.testing.assert_close(ms[1].displacement(t)[1, 1], torch.tensor(-0.5, **f64))
    torch.testing.assert_close(ms[2].displacement(t)[2, 0], torch.tensor(0.375, **f64))
    torch.testing.assert_close(ms[3].displacement(t)[2, 2], torch.tensor(0.75, **f64))
    spin = parse_motions({"type": "spin", "axis": [0, 1, 0], "turns": 1.0}, "test", "m")[0]
    R = spin.rotation(torch.tensor([0.25], **f64))[0]
    torch.testing.assert_close(R @ torch.tensor([1.0, 0, 0], **f64),
                               torch.tensor([0, 0, -1.0], **f64))


def test_texture_moves_with_the_object():
    cfg = {"objects": [{"type": "sphere", "radius": 0.5, "position": [0, 0, 0],
                        "texture": {"type": "stripes", "colors": [[1, 1, 1], [0, 0, 0]],
                                    "period": 0.2, "axis": [1, 0, 0]},
                        "motion": {"type": "spin", "axis": [0, 1, 0], "turns": 1.0}}],
           "light": {"ambient": 1.0, "intensity": 0.0}}
    r = Renderer(parse_scene(cfg, "test"))
    o = torch.tensor([[0.05, 0, -3.0]], **f64).repeat(2, 1)
    d = torch.tensor([[0, 0, 1.0]], **f64).repeat(2, 1)
    a = r.radiance(o, d, torch.tensor([0.0, 0.5], **f64))
    # half a turn mirrors x: the point at local x = +0.05 shows the stripe of x = −0.05
    assert not torch.equal(a[0], a[1])


def test_interval_spheres_contain_the_object():
    cfg = {"objects": [{"type": "box", "size": [0.2, 0.1, 0.3], "position": [0, -0.2, 0],
                        "motion": [{"type": "orbit", "radius": 0.3, "turns": 2},
                                   {"type": "bounce", "height": 0.2, "bounces": 3}]}]}
    obj = parse_scene(cfg, "test").objects[0]
    c, r = obj.interval_spheres(20, sub=4)
    t = torch.rand(2000, **f64)
    centre = obj.pose(t)[1].numpy()
    k = np.minimum((t.numpy() * 20).astype(int), 19)
    assert np.all(np.linalg.norm(centre - c[k], axis=1) + obj.bound_radius <= r[k] + 1e-12)


def test_scene_errors_name_the_field():
    with pytest.raises(InputError, match=r"objects\[0\].radius"):
        parse_scene({"objects": [{"type": "sphere", "radius": -1}]}, "scene x")
    with pytest.raises(InputError, match=r"objects\[0\].type: expected one of sphere, box"):
        parse_scene({"objects": [{"type": "cone"}]}, "scene x")
    with pytest.raises(InputError, match=r"objects\[0\].motion"):
        parse_scene({"objects": [{"type": "plane", "height": 0.3,
                                  "motion": {"type": "linear", "to": [1, 0, 0]}}]}, "scene x")
