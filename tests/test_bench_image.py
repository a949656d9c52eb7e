"""``python -m benchmarks image``: the default job's field and renderer, any commit's code."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from benchmarks import bench_image
from eventrecon.render.cameras import ring_rig

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("n_fine", [32, 0])
def test_a_fresh_field_is_asked_every_sample_of_every_ray_that_meets_the_cylinder(n_fine):
    """An untrained field (seed 0) with a fresh, fully occupied grid: each ray that meets
    the clipping cylinder sends all its coarse and fine samples to the field (none of its
    rays is opaque enough to stop early), a ray that misses sends none; so the samples
    per pixel are ``(n_coarse + n_fine)`` times the share of rays that hit."""
    torch.manual_seed(0)
    cfg = bench_image._config(REPO, ["scale=cpu", f"render.n_fine={n_fine}"], None)
    field, renderer = bench_image._field_and_renderer(cfg, None)
    rig = dict(cfg.scene.rig)
    row = bench_image.time_images(field, renderer, rig, 1, 24, 18, warmup=0)
    cams = ring_rig(3, 24, 18, radius=rig["radius"], elevation_deg=rig["elevation_deg"],
                    fov_deg=rig["fov_deg"], target=tuple(rig["target"]))
    o, d = cams.image_rays(0)
    hit = renderer.cylinder.ray_interval(o, d)[2].float().mean().item()
    assert 0.2 < hit < 1.0                           # some rays miss, most hit
    assert renderer.n_fine == n_fine
    assert row["samples_per_px"] == pytest.approx((renderer.n_coarse + n_fine) * hit)
    assert len(row["seconds"]) == 1 and row["median_s"] > 0


def test_a_call_with_no_rows_is_answered_without_the_field():
    """Older renderers ask the field for zero rows where a chunk misses the cylinder;
    the guard answers with empty outputs and passes every other call through."""
    calls: list[int] = []

    class Field:
        def forward(self, xyz: torch.Tensor, t: torch.Tensor):
            calls.append(xyz.shape[0])
            return xyz.sum(-1), xyz * 2

    f = Field()
    bench_image._guard_empty(f)
    sigma, rgb = f.forward(torch.zeros(0, 3), torch.zeros(0, 1))
    assert sigma.shape == (0,) and rgb.shape == (0, 3) and calls == []
    xyz = torch.arange(6.0).reshape(2, 3)
    sigma, rgb = f.forward(xyz, torch.zeros(2, 1))
    assert calls == [2] and sigma.tolist() == [3.0, 12.0] and torch.equal(rgb, xyz * 2)
