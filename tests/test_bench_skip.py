"""The skip benchmark's split of samples per ray into the coarse and the fine level."""

from __future__ import annotations

import math

import pytest
import torch
from test_occupancy import CYL, Blob, _rays

from benchmarks.bench_skip import parse_grid, ray_samples, rebuilt_grid
from eventrecon.render import volume
from eventrecon.render.volume import Renderer


def _batches(n_batches: int, n_rays: int) -> list[dict]:
    out = []
    for i in range(n_batches):
        o, d, t, bg = _rays(n_rays, 10 + i)
        out.append({"rays_o": o, "rays_d": d, "t0": t, "t1": (t + 0.1).clamp(max=1.0),
                    "t_ref": (t - 0.1).clamp(min=0.0), "bg": bg})
    return out


def test_without_a_grid_every_sample_of_both_levels_counts():
    r, batches = Renderer(n_coarse=32, n_fine=24, **CYL), _batches(2, 50)
    hit = torch.cat([r.cylinder.ray_interval(b["rays_o"], b["rays_d"])[2] for b in batches])
    share = float(hit.float().mean())                  # a ray that misses costs nothing
    assert 0.9 < share < 1.0
    counted = ray_samples(r, Blob(), batches)
    assert counted["coarse"] == pytest.approx(32 * share)
    assert counted["fine"] == pytest.approx(24 * share)
    assert counted["fine_faint"] == counted["fine_other"] == 24   # every hit takes all
    assert r.n_fine == 24                              # restored


def test_the_coarse_count_is_the_renderers_own_at_the_fine_draws(monkeypatch):
    """The split against the renderer's counter read inside one full render, at the moment
    the fine samples are drawn (after the coarse level, before the fine one), with a grid
    that skips most of the box."""
    field, batches = Blob(), _batches(3, 60)
    # PyTorch's passes, as ray_samples counts them (the compiled ones ask the same samples)
    r = Renderer(n_coarse=32, n_fine=32, skip="grid", compiled=False, **CYL)
    r.occupancy = rebuilt_grid(r, field, 24, 16, (1, 0), 0.01, passes=3)
    counted = ray_samples(r, field, batches)
    coarse, fine, opaque = counted["coarse"], counted["fine"], counted["opaque"]
    seen: list[int] = []                               # coarse inputs of each render
    start = [0]
    draw = volume.sample_pdf

    def counting(*args, **kwargs):
        seen.append(r.field_inputs - start[0])
        return draw(*args, **kwargs)

    monkeypatch.setattr(volume, "sample_pdf", counting)
    r.field_inputs, rays, hits = 0, 0, 0
    for i, b in enumerate(batches):
        o, d = b["rays_o"].repeat(3, 1), b["rays_d"].repeat(3, 1)
        t = torch.cat([b["t0"], b["t1"], b["t_ref"]], 0)
        start[0] = r.field_inputs
        out = r(field, o, d, t, b["bg"].repeat(3, 1), perturb=True,
                gen=torch.Generator().manual_seed(i), copies=3)
        hits += int((out[-1]["opacity"].detach() > 0.5).sum())
        rays += o.shape[0]
    assert len(seen) == len(batches)
    assert coarse == pytest.approx(sum(seen) / rays, abs=1e-9)
    assert coarse + fine == pytest.approx(r.field_inputs / rays, abs=1e-9)
    assert opaque == pytest.approx(hits / rays, abs=1e-9)
    assert 0 < coarse < 16 and 0 < fine < 32           # the blob fills little of the box
    assert 0 < opaque < 0.5


def test_a_grid_is_named_as_cells_bins_and_dilation():
    assert parse_grid("48x16:0,0") == (48, 16, (0, 0))
    with pytest.raises(SystemExit, match="RxB:s,b"):
        parse_grid("48x16")


def test_fine_inputs_by_coarse_opacity_add_up_to_the_fine_count():
    """The fine inputs counted per ray add up to the fine count of the renderer's own
    counter, with a grid that skips most of the box; the renderer's own ``_query`` is
    back afterwards; without a fine level there is nothing to split (NaN)."""
    field, batches = Blob(), _batches(3, 60)
    r = Renderer(n_coarse=32, n_fine=32, skip="grid", **CYL)
    r.occupancy = rebuilt_grid(r, field, 24, 16, (1, 0), 0.01, passes=3)
    c = ray_samples(r, field, batches)
    hits = sum(int(r.cylinder.ray_interval(b["rays_o"], b["rays_d"])[2].sum()) for b in batches)
    per_hit = c["faint"] * c["fine_faint"] + (1 - c["faint"]) * c["fine_other"]
    assert per_hit * 3 * hits / (3 * 60 * len(batches)) == pytest.approx(c["fine"], rel=1e-6)
    assert 0 < c["faint"] < 1 and c["fine_faint"] < c["fine_other"] <= 32
    assert c["faint_fine"] == pytest.approx(
        c["faint"] * c["fine_faint"] / per_hit, rel=1e-6)
    assert "_query" not in vars(r)                     # the renderer's own method again
    coarse_only = Renderer(n_coarse=32, n_fine=0, **CYL)
    assert math.isnan(ray_samples(coarse_only, field, batches)["faint"])
