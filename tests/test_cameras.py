"""Camera model: distortion round trip, projection of rays, camdict round trip."""

import torch

from eventrecon.render.cameras import cameras_from_camdict, cameras_to_camdict, ring_rig
from eventrecon.render.distortion import distort, undistort

STRONG = (-0.4, 0.2, 1e-3, -2e-3, -0.05)  # like the real rig (k1 ≈ −0.4)


def test_undistort_inverts_distort_over_whole_image():
    cams = ring_rig(1, 346, 260, fov_deg=60.0, dist=STRONG)
    uv = cams.pixel_grid()
    view = torch.zeros(len(uv), dtype=torch.long)
    o, _ = cams.rays(view, uv)
    d_cam = cams.pixel_directions(view, uv)  # undistorted, z = 1
    # project(undistort(p)) = p to 1e-4 px for every pixel
    xy = distort(d_cam[:, :2], cams.dist[view])
    u = cams.K[0, 0, 0] * xy[:, 0] + cams.K[0, 0, 2]
    v = cams.K[0, 1, 1] * xy[:, 1] + cams.K[0, 1, 2]
    err = (torch.stack([u, v], -1) - uv).abs().max().item()
    assert err < 1e-4


def test_rays_project_back_to_their_pixels():
    cams = ring_rig(3, 64, 48, dist=STRONG)
    uv = torch.rand(500, 2, dtype=torch.float64) * torch.tensor([63.0, 47.0])
    view = torch.randint(0, 3, (500,))
    o, d = cams.rays(view, uv)
    uv2, z = cams.project(o.double() + 2.0 * d.double(), view)
    assert (uv2 - uv).abs().max().item() < 1e-3  # float32 rays
    assert (z > 0).all()


def test_undistort_known_value():
    d = torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    # x (1 + 0.1 x²) = 0.5125 has the root x = 0.5
    x = undistort(torch.tensor([[0.5125, 0.0]], dtype=torch.float64), d)
    assert abs(x[0, 0].item() - 0.5) < 1e-12


def test_camdict_round_trip():
    cams = ring_rig(4, 80, 60, dist=STRONG)
    back = cameras_from_camdict(cameras_to_camdict(cams))
    assert torch.allclose(back.K, cams.K) and torch.allclose(back.dist, cams.dist)
    assert torch.allclose(back.c2w, cams.c2w, atol=1e-12)
    assert (back.width, back.height) == (80, 60)


def test_ring_rig_looks_at_target():
    cams = ring_rig(6, 64, 48, target=(0.0, -0.25, 0.0))
    uv, z = cams.project(torch.tensor([[0.0, -0.25, 0.0]] * 6), torch.arange(6))
    assert torch.allclose(uv, torch.tensor([[31.5, 23.5]] * 6, dtype=torch.float64), atol=1e-9)
    assert torch.allclose(z, torch.full((6,), 2.5, dtype=torch.float64))
