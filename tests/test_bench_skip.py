"""The skip benchmark's split of samples per ray into the coarse and the fine level."""

from __future__ import annotations

import pytest
import torch
from test_occupancy import CYL, Blob, _rays

from benchmarks.bench_skip import parse_grid, ray_samples, rebuilt_grid
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
    coarse, fine = ray_samples(r, Blob(), batches)
    assert coarse == pytest.approx(32 * share) and fine == pytest.approx(24 * share)
    assert r.n_fine == 24                              # restored


def test_the_split_adds_up_to_the_renderers_own_count_and_the_grid_cuts_both_levels():
    field, batches = Blob(), _batches(3, 60)
    r = Renderer(n_coarse=32, n_fine=32, skip="grid", **CYL)
    r.occupancy = rebuilt_grid(r, field, 24, 16, (1, 0), 0.01, passes=3)
    coarse, fine = ray_samples(r, field, batches)
    r.field_inputs, rays = 0, 0                        # the same renders, counted at once
    for i, b in enumerate(batches):
        o, d = b["rays_o"].repeat(3, 1), b["rays_d"].repeat(3, 1)
        t = torch.cat([b["t0"], b["t1"], b["t_ref"]], 0)
        with torch.no_grad():
            r(field, o, d, t, b["bg"].repeat(3, 1), perturb=True,
              gen=torch.Generator().manual_seed(i), copies=3)
        rays += o.shape[0]
    assert coarse + fine == pytest.approx(r.field_inputs / rays, abs=1e-9)
    assert 0 < coarse < 16 and 0 < fine < 32           # the blob fills little of the box
    assert r.occupancy.dilation == (1, 0) and r.occupancy.time_bins == 16


def test_a_grid_is_named_as_cells_bins_and_dilation():
    assert parse_grid("48x16:0,0") == (48, 16, (0, 0))
    with pytest.raises(SystemExit, match="RxB:s,b"):
        parse_grid("48x16")
