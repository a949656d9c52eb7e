"""Exact ray-primitive intersections, shading, motions and textures against known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from eventrecon.common.errors import InputError
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


MIXED = {
    "objects": [
        {"type": "plane", "height": 0.3, "radius": 1.5,
         "texture": {"type": "checker", "colors": [[0.2, 0.2, 0.2], [0.7, 0.7, 0.6]], "size": 0.2}},
        {"type": "box", "size": [0.2, 0.1, 0.15], "position": [0.3, 0.1, -0.2],     # static prop
         "texture": {"type": "solid", "color": [0.4, 0.6, 0.2]}},
        {"type": "group", "name": "body", "position": [0, -0.2, 0],
         "motion": [{"type": "spin", "axis": [0, 1, 0], "turns": 0.7},
                    {"type": "linear", "to": [0.05, 0, 0.02]}]},
        {"type": "box", "parent": "body", "size": [0.3, 0.08, 0.2], "position": [0, 0.05, 0],
         "orientation": {"axis": [1, 0, 1], "deg": 20},
         "texture": {"type": "stripes", "colors": [[0.9, 0.1, 0.1], [0.9, 0.9, 0.2]],
                     "period": 0.05, "axis": [1, 1, 0]}},
        {"type": "sphere", "parent": "body", "radius": 0.06, "position": [0.15, -0.05, 0.05],
         "texture": {"type": "checker", "colors": [[0.1, 0.1, 0.9], [0.9, 0.9, 0.9]],
                     "size": 0.03}},
        {"type": "group", "name": "arm", "parent": "body", "position": [-0.15, -0.02, 0],
         "motion": {"type": "keyframe", "axis": [0, 0, 1],
                    "keys": [[0, 0, 0, 0, 0], [0.3, 0, 0, 0, 50], [0.6, 0, 0, 0, 50],
                             [1, 0, 0, 0, -20]]}},
        {"type": "box", "parent": "arm", "size": [0.2, 0.02, 0.03], "position": [-0.1, 0, 0],
         "texture": {"type": "checker", "colors": [[0.2, 0.8, 0.2], [0.1, 0.1, 0.1]],
                     "size": 0.04}},
        {"type": "box", "parent": "arm", "size": [0.05, 0.05, 0.05], "position": [-0.2, 0, 0],
         "motion": {"type": "spin", "axis": [1, 0, 0], "turns": 2.0}},
        {"type": "sphere", "radius": 0.07, "position": [0.1, -0.45, 0.15],
         "motion": {"type": "bounce", "height": 0.1, "bounces": 2}},
        {"type": "skirt", "parent": "body", "position": [0.0, 0.25, 0.0],
         "rings": [[-0.05, 0.06], [0.05, 0.12]], "flare": {"amplitude": 0.3, "cycles": 1},
         "texture": {"type": "stripes", "colors": [[0.8, 0.3, 0.6], [0.3, 0.8, 0.6]],
                     "period": 0.04, "axis": [1, 0, 0]}},
    ],
    "light": {"direction": [0.3, -1.0, 0.4], "ambient": 0.2, "intensity": 0.8},
    "background": [0.1, 0.2, 0.3],
}


def _reference_world(obj, t):
    """``(R [N, 3, 3], c [N, 3])`` composed by hand from each node's own pose."""
    R, c = obj.pose(t)
    R = R.expand(len(t), 3, 3) if R.dim() == 2 else R
    if obj.parent is None:
        return R, c
    Rp, cp = _reference_world(obj.parent, t)
    return Rp @ R, (Rp @ c[..., None])[..., 0] + cp


def _reference_radiance(scene, o, d, t):
    """Nearest hit over every object separately (no culling, no batching, no cache)."""
    from eventrecon.sim.skirt import intersect_skirt

    n = o.shape[0]
    best = torch.full((n,), float("inf"), **f64)
    rgb = scene.background[None].repeat(n, 0)
    index = torch.full((n,), -1)
    lt = torch.as_tensor(scene.light.direction)
    for i, obj in enumerate(scene.objects):
        if obj.kind == "group":
            continue
        if obj.kind == "plane":
            s = intersect_plane(o, d, obj.height)
            p = o + torch.nan_to_num(s, posinf=0)[:, None] * d
            s = torch.where(p[:, 0] ** 2 + p[:, 2] ** 2 <= obj.radius ** 2, s, float("inf"))
            nw, pl = torch.tensor([0, -1.0, 0], **f64).expand(n, 3), p - torch.tensor(
                [0, obj.height, 0], **f64)
        else:
            R, c = _reference_world(obj, t)
            ol = torch.einsum("nji,nj->ni", R, o - c)
            dl = torch.einsum("nji,nj->ni", R, d)
            if obj.kind == "sphere":
                s = intersect_sphere(ol, dl, obj.radius)
                pl = ol + torch.nan_to_num(s, posinf=0)[:, None] * dl
                nl = pl / obj.radius
            elif obj.kind == "box":
                s, nl = intersect_box(ol, dl, torch.as_tensor(obj.half_size))
                pl = ol + torch.nan_to_num(s, posinf=0)[:, None] * dl
            else:
                s, nl, pl = intersect_skirt(ol, dl, t, obj.skirt)
            nw = torch.einsum("nij,nj->ni", R, nl)
        win = s < best
        shade = scene.light.ambient + scene.light.intensity * (nw @ lt).clamp_min(0)
        col = obj.texture.albedo(pl) * shade[:, None] * torch.as_tensor(scene.light.color)
        best, index = torch.where(win, s, best), torch.where(win, i, index)
        rgb = torch.where(win[:, None], col, torch.as_tensor(rgb))
    return torch.as_tensor(rgb), index


@pytest.fixture
def one_thread():
    """Many small tensor operations: one thread is faster (as the simulator runs)."""
    from eventrecon.sim.pipeline import torch_threads

    with torch_threads(1):
        yield


def test_batched_renderer_equals_a_per_object_reference(one_thread):
    """Groups (nested, moving and on keyframes), boxes fixed in them or with their own
    motion, spheres, a skirt, a floor and a static prop: the renderer (bodies, box and
    sphere sets, world-hull culling) and the pixel renderer (static hits cached) give
    the radiance and hit object of an object-by-object reference."""
    from eventrecon.render.cameras import ring_rig
    from eventrecon.sim.raytrace import PixelRenderer

    scene = parse_scene(MIXED, "test")
    cams = ring_rig(3, 40, 30, radius=1.6, fov_deg=40, target=(0, -0.1, 0))
    prend = PixelRenderer(scene, cams)
    gen = torch.Generator().manual_seed(0)
    pix = torch.randint(0, prend.n_pixels, (6000,), generator=gen)
    t = torch.rand(6000, generator=gen, **f64)
    o, d = prend.o[pix, 0], prend.d[pix, 0]
    ref, idx = _reference_radiance(scene, o, d, t)
    assert (idx >= 0).float().mean() > 0.3 and len(set(idx.tolist())) >= 8
    torch.testing.assert_close(Renderer(scene).radiance(o, d, t), ref, rtol=0, atol=1e-12)
    torch.testing.assert_close(prend.radiance(pix, t), ref, rtol=0, atol=1e-12)
    hit = prend.trace(pix, t)
    assert torch.equal(hit.index, idx)


def test_group_pose_composes_and_children_inherit():
    """A child of a spinning group is carried round the group's origin; it moves (and
    so is subject) though it has no motion of its own; ``subject`` is inherited."""
    scene = parse_scene({"objects": [
        {"type": "group", "name": "g", "position": [0.2, -0.3, 0], "subject": True},
        {"type": "group", "name": "j", "parent": "g", "position": [0.1, 0, 0],
         "motion": {"type": "spin", "axis": [0, 1, 0], "turns": 1.0}},
        {"type": "sphere", "parent": "j", "radius": 0.02, "position": [0.1, 0, 0]},
        {"type": "box", "parent": "g", "size": [0.1, 0.1, 0.1]}]}, "test")
    g, j, sph, box = scene.objects
    R, c = sph.world_pose(torch.tensor([0.0, 0.25, 0.5], **f64))
    torch.testing.assert_close(c, torch.tensor([[0.4, -0.3, 0], [0.3, -0.3, -0.1],
                                                [0.2, -0.3, 0]], **f64), rtol=0, atol=1e-15)
    assert sph.moves and not sph.moves_self and not box.moves
    assert box.subject and not box.in_background and not sph.in_background
    assert [o for o in scene.moving] == [sph]
    # the group's hull holds its descendants at all times
    centre, rad = g.hull()
    assert rad >= 0.1 + 0.1 + 0.02 - 1e-12


def test_activity_is_conservative_with_joints_at_rest(one_thread):
    """Busy flags per interval: every pixel whose radiance changes inside an interval is
    busy there; a keyframe joint at rest (t in [0.3, 0.6]) makes no pixel busy."""
    from eventrecon.render.cameras import ring_rig
    from eventrecon.sim.raytrace import PixelRenderer

    arm = [o for o in MIXED["objects"] if o.get("name") == "arm" or o.get("parent") == "arm"]
    arm = [{k: v for k, v in arm[0].items() if k != "parent"} | {"position": [0, -0.2, 0]},
           *arm[1:]]
    bounce = [o for o in MIXED["objects"] if o["type"] == "sphere" and "motion" in o]
    K = 20
    fixed = [o for o in arm if "motion" not in o or o.get("name") == "arm"]
    for objects in (arm + bounce, fixed):
        scene = parse_scene({**MIXED, "objects": objects}, "test")
        prend = PixelRenderer(scene, ring_rig(2, 24, 18, radius=1.2, fov_deg=40,
                                              target=(0, -0.2, 0)))
        pix, busy = prend.activity(K)
        full = torch.zeros(prend.n_pixels, K, dtype=torch.bool)
        full[torch.as_tensor(pix)] = torch.as_tensor(busy)
        g = torch.arange(prend.n_pixels)
        n_changed = []
        for k in range(K):
            ts = torch.linspace(k / K, (k + 1) / K, 5, **f64)
            imgs = torch.stack([prend.radiance(g, ts[i].expand(len(g))) for i in range(5)])
            changed = (imgs != imgs[0]).any(-1).any(0)
            assert not (changed & ~full[:, k]).any(), k
            n_changed.append(int(changed.sum()))
        assert min(n_changed[:6]) > 2                       # things move, visibly
    assert not full[:, 6:12].any() and full[:, :6].any(1).sum() > 15   # the arm rests


def test_hierarchy_errors_name_the_field():
    box = {"type": "box", "size": [0.1, 0.1, 0.1]}
    with pytest.raises(InputError, match=r"objects\[1\]\.parent: expected the name of a group "
                                         r"listed earlier \(arm\), got 'leg'"):
        parse_scene({"objects": [{"type": "group", "name": "arm"}, {**box, "parent": "leg"}]},
                    "scene x")
    with pytest.raises(InputError, match=r"objects\[0\]\.parent: expected the name of a group "
                                         r"listed earlier \(none so far\)"):
        parse_scene({"objects": [{**box, "parent": "arm"}, {"type": "group", "name": "arm"}]},
                    "scene x")
    with pytest.raises(InputError, match=r"objects\[1\]\.name: expected a name no other object"):
        parse_scene({"objects": [{"type": "group", "name": "a"}, {**box, "name": "a"}]}, "s")
    with pytest.raises(InputError, match=r"objects\[1\]\.parent: expected no parent"):
        parse_scene({"objects": [{"type": "group", "name": "a"},
                                 {"type": "plane", "height": 0.3, "parent": "a"}]}, "s")


def test_interval_bounds_hold_a_long_box_on_a_joint():
    """The sub-box spheres of a long thin box carried by a turning joint hold its whole
    surface over each interval (points sampled densely in time and on the faces), and
    are much tighter than one sphere about its centre."""
    scene = parse_scene({"objects": [
        {"type": "group", "name": "j", "position": [0, -0.2, 0],
         "motion": {"type": "keyframe", "axis": [0, 0, 1],
                    "keys": [[0, 0, 0, 0, 0], [1, 0.1, 0, 0, 90]]}},
        {"type": "box", "parent": "j", "size": [0.4, 0.02, 0.05], "position": [0.2, 0, 0],
         "orientation": {"axis": [0, 1, 0], "deg": 10}}]}, "test")
    box = scene.objects[1]
    K = 8
    centres, radii = box.interval_bounds(K, sub=4)                     # [m, K, 3], [m, K]
    single = box.interval_spheres(K, sub=4)[1]
    assert centres.shape[0] == 4 and (radii.mean(0) < 0.45 * single).all()
    g = np.linspace(-1, 1, 9)
    faces = []
    for ax in range(3):
        for sign in (-1.0, 1.0):
            for a in g:
                for b in g:
                    p = np.insert(np.array([a, b]), ax, sign)
                    faces.append(p)
    local = np.array(faces) * box.half_size                           # the box's surface
    for k in range(K):
        t = torch.linspace(k / K, (k + 1) / K, 41, **f64)
        R, c = box.world_pose(t)
        pts = (torch.einsum("tij,pj->tpi", R, torch.as_tensor(local)) + c[:, None]).numpy()
        dist = np.linalg.norm(pts[:, :, None] - centres[None, None, :, k], axis=-1)
        assert (dist <= radii[None, None, :, k]).any(-1).all(), k
