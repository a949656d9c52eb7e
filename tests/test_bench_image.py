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


def test_step_sets_a_fresh_fields_band_window_and_is_refused_where_it_cannot_apply(
        tmp_path, monkeypatch):
    """``--step 20`` renders the default job's fresh NeRF with the band window of step 20
    (of the paper's 4000-step annealing: the first position and time bands partly on,
    the rest off), as issue 12's 20-step command leaves it with today's code; ``--step``
    with ``--run``, or a negative one, stops with a usage error before any work."""
    from eventrecon.fields.encoding import band_window
    seen = {}
    real = bench_image.time_images

    def spy(field, *args, **kwargs):
        seen["windows"] = [field.pos_enc.window.tolist(), field.time_enc.window.tolist()]
        return real(field, *args, **kwargs)

    monkeypatch.setattr(bench_image, "time_images", spy)
    out = tmp_path / "row.json"
    bench_image.main(["--step", "20", "--images", "1", "--warmup", "0", "--width", "16",
                      "--height", "12", "--json", str(out)])
    assert seen["windows"] == [pytest.approx(band_window(14, 20, 4000)),
                               pytest.approx(band_window(7, 20, 4000))]
    assert seen["windows"][0][0] > 0 and seen["windows"][0][1] == 0 == seen["windows"][1][1]
    assert '"step": 20' in out.read_text()
    for argv in (["--run", str(tmp_path), "--step", "3"], ["--step", "-1"]):
        with pytest.raises(SystemExit) as exc:
            bench_image.main(argv)
        assert exc.value.code == 2
