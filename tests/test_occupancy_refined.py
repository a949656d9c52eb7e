"""The two-level occupancy grid: its mask, updates, state, configuration and renders."""

from __future__ import annotations

import itertools

import pytest
import torch
import torch.nn.functional as F
from test_occupancy import CYL, Blob, _rays

from eventrecon.errors import InputError
from eventrecon.render.occupancy import OccupancyGrid, dilate
from eventrecon.render.occupancy_refined import RefinedGrid, build_grid
from eventrecon.render.volume import Renderer


def _updated(field, steps: int, **grid) -> Renderer:
    """A renderer whose grid had ``steps`` updates from ``field``."""
    r = Renderer(n_coarse=32, n_fine=32, skip="grid", occupancy=grid, **CYL)
    for step in range(steps):
        r.occupancy.update(lambda x, t: r.masked_density(field, x, t),
                           torch.Generator().manual_seed(step))
    return r


@pytest.mark.parametrize(("s", "b"), list(itertools.product([0, 1, 2], [0, 1, 3, 6])))
def test_dilate_is_the_or_over_the_neighbourhood(s: int, b: int) -> None:
    """Against max pooling of the 0/1 grid in space and a shift in time, one bin at a time."""
    core = torch.rand(5, 7, 7, 7, generator=torch.Generator().manual_seed(s + 5 * b)) < 0.05
    ref = core.float()
    if s:
        ref = F.max_pool3d(ref[:, None], 2 * s + 1, stride=1, padding=s)[:, 0]
    for _ in range(b):
        ref = torch.maximum(ref, torch.cat([ref[1:], ref[-1:]]))
        ref = torch.maximum(ref, torch.cat([ref[:1], ref[:-1]]))
    assert torch.equal(dilate(core, s, b), ref > 0)


def test_the_mask_is_the_gate_and_the_dilated_gated_fine_cells() -> None:
    """Set by hand: the refined mask against a reference built from the indices."""
    g = RefinedGrid([-1, -1, -1], [1, 1, 1], resolution=4, time_bins=2, threshold=0.5,
                    dilation=(0, 0), refine=(2, 2), refine_dilation=(1, 0))
    g.asked.fill_(True)
    g.density[1, 2, 1, 3] = 1.0                  # one occupied coarse cell
    g.fine_asked.fill_(True)
    g.fine_asked[0, 0, 0, 0] = False             # unasked, but under a closed gate
    g.fine_density[2, 4, 2, 6] = 1.0             # inside the coarse cell: its corner child
    g.fine_density[0, 7, 7, 7] = 1.0             # dense but under a closed gate
    g.refresh()
    idx = torch.stack(torch.meshgrid(*(torch.arange(n) for n in g.fine_occ.shape),
                                     indexing="ij"))
    gate = (idx[0] // 2 == 1) & (idx[1] // 2 == 2) & (idx[2] // 2 == 1) & (idx[3] // 2 == 3)
    near = torch.zeros_like(gate)
    far = (idx - torch.tensor([2, 4, 2, 6])[:, None, None, None, None]).abs()
    near |= (far[0] == 0) & (far[1:] <= 1).all(0)
    assert torch.equal(g.occupancy, gate & near)
    # the corner child keeps the 2³ cells of its parent in its own bin, of the parent's 16
    assert int(g.occupancy.sum()) == 8 and int(gate.sum()) == 16
    # the mask never keeps more than the coarse grid's
    assert bool((g.occupancy <= g.gate()).all())


def test_no_sample_above_the_threshold_is_skipped_and_the_refinement_skips_more() -> None:
    """The blob test of ``test_occupancy.py``: every point above the threshold is in an
    occupied cell of the refined grid, which keeps a fifth less than the coarse grid."""
    field = Blob()
    grid = {"resolution": 16, "time_bins": 8, "threshold": 0.05, "fraction": 1.0,
            "recheck": 0.25}
    coarse = _updated(field, 12, **grid).occupancy
    fine = _updated(field, 12, **grid, refine=[2, 4], refine_budget=10**7).occupancy
    assert isinstance(fine, RefinedGrid) and not isinstance(coarse, RefinedGrid)
    g = torch.Generator().manual_seed(9)
    x = fine.lo + torch.rand(400_000, 3, generator=g) * (fine.hi - fine.lo)
    t = torch.rand(400_000, 1, generator=g)
    dens = Renderer(**CYL).masked_density(field, x, t)
    above = dens > 0.05
    assert above.sum() > 1000
    assert bool(fine.occupied(x, t)[above].all())
    assert bool(coarse.occupied(x, t)[above].all())
    assert fine.occupied_fraction() < 0.8 * coarse.occupied_fraction()
    # the same coarse level in both
    assert torch.equal(fine.occ, coarse.occ)


def test_updates_ask_under_open_gates_within_the_budget_and_forget_under_closed_ones() -> None:
    grid = RefinedGrid([-1, -1, -1], [1, 1, 1], resolution=8, time_bins=2, threshold=0.01,
                       fraction=0.25, recheck=0.25, dilation=(0, 0), refine=(2, 2),
                       refine_budget=300)

    def slab(x, t):                              # σ = 1 on x > 0.5 (a quarter of the box)
        return (x[:, 0] > 0.5).float()

    def narrow(x, t):                            # the field leaves 0.5 < x < 0.75
        return (x[:, 0] > 0.75).float()

    grid.update(slab, torch.Generator().manual_seed(0))      # the coarse cells all asked
    asked = [grid.update(slab, torch.Generator().manual_seed(s)) for s in range(1, 41)]
    # coarse: a quarter of the 256 dense cells and of the 768 empty ones per update; fine:
    # the budget, shared between the unasked cells and the re-asks
    fine_mean = sum(asked) / 40 - 0.25 * (8 * 8 * 8 * 2)
    assert 0.8 * 300 <= fine_mean <= 1.2 * 300
    assert bool((grid.fine_asked <= grid.gate()).all())      # nothing kept under a closed gate
    was_asked = grid.fine_asked.clone()
    # the field leaves a slab: its gates close, the fine cells under them are forgotten
    probe = torch.tensor([[0.6, 0.1, 0.1]])
    for s in range(100, 400):
        grid.update(narrow, torch.Generator().manual_seed(s))
        if not grid.occupied(probe, torch.zeros(1, 1)).any():
            break
    closed = was_asked & ~grid.gate()
    assert closed.sum() > 100
    assert not grid.fine_asked[closed].any()
    # reopened, the fine cells count as occupied until asked
    grid.asked.fill_(False)
    grid.refresh()
    assert bool(grid.occupancy.all())


def test_a_wide_gate_pauses_and_forgets_the_fine_level_and_reasks_never_stop() -> None:
    """Above ``refine_below`` nothing is asked and the mask is the gate; below it, with
    more unasked cells than the budget, half the budget still re-asks cells."""
    grid = RefinedGrid([-1, -1, -1], [1, 1, 1], resolution=8, time_bins=1, threshold=0.01,
                       fraction=0.25, recheck=0.25, dilation=(0, 0), refine=(4, 1),
                       refine_budget=400, refine_below=0.3)

    def half(x, t):                              # σ = 1 on x > 0: the gate covers half
        return (x[:, 0] > 0).float()

    def quarter(x, t):                           # σ = 1 on x > 0.5: a quarter
        return (x[:, 0] > 0.5).float()

    for s in range(3):
        grid.update(quarter, torch.Generator().manual_seed(s))
    assert grid.fine_asked.any()
    n_gate = int(grid.gate().sum())              # 8 × 8 × 2 coarse cells × 4³
    assert n_gate == 128 * 64
    # with 8192 gated cells and a budget of 400, the asked ones keep getting re-asked
    seen = grid.fine_asked.view(-1)[grid.gate().view(-1)]
    chosen, _ = grid._choose(grid.gate().view(-1).nonzero().squeeze(1), seen,
                             torch.Generator().manual_seed(7))
    reasked = int((chosen & seen).sum())
    assert reasked >= 100 and int(chosen.sum()) <= 1.3 * 400
    # the field widens past refine_below: paused, forgotten, the mask is the gate
    for s in range(3, 6):
        asked = grid.update(half, torch.Generator().manual_seed(s))
    assert float(grid.gate().float().mean()) > 0.3
    assert not grid.fine_asked.any()
    assert torch.equal(grid.occupancy, grid.gate())
    assert asked <= 1024                         # the coarse level's asks alone


def test_the_refined_grid_resumes_exactly_and_renders_with_fewer_samples() -> None:
    field = Blob()
    cfg = {"resolution": 16, "time_bins": 8, "threshold": 0.01, "refine": [2, 4]}
    r = _updated(field, 4, **cfg)
    again = Renderer(n_coarse=32, n_fine=32, skip="grid", occupancy=dict(cfg), **CYL)
    again.load_state_dict({k: v.clone() for k, v in r.state_dict().items()})
    assert torch.equal(again.occupancy.occupancy, r.occupancy.occupancy)
    assert r.occupancy.fine_asked.any()
    assert not torch.equal(r.occupancy.occupancy, r.occupancy.gate())
    for rr in (r, again):
        rr.occupancy.update(lambda x, tt, rr=rr: rr.masked_density(field, x, tt),
                            torch.Generator().manual_seed(42))
    assert torch.equal(again.occupancy.fine_density, r.occupancy.fine_density)
    assert torch.equal(again.occupancy.occupancy, r.occupancy.occupancy)
    # renders: fewer field inputs than the coarse grid alone, the same image within 1e-3
    coarse = _updated(field, 4, resolution=16, time_bins=8, threshold=0.01)
    dense = Renderer(n_coarse=32, n_fine=32, **CYL)
    o, d, t, bg = _rays(400, 3)
    counts = []
    with torch.no_grad():
        ref = dense(field, o, d, t, bg)[-1]["rgb"]
        for rr in (coarse, r):
            rr.field_inputs = 0
            out = rr(field, o, d, t, bg)[-1]["rgb"]
            counts.append(rr.field_inputs)
            assert (out - ref).abs().max().item() <= 1e-3
    assert counts[1] < 0.8 * counts[0]


def test_the_compiled_lookup_reads_the_refined_mask() -> None:
    field = Blob()
    r = _updated(field, 3, resolution=8, time_bins=4, threshold=0.01, refine=[3, 2])
    o, d, t, _ = _rays(300, 4)
    s = torch.linspace(1.5, 3.5, 48).expand(300, 48).contiguous()
    n, k = s.shape
    grid = r.occupancy
    assert grid.fine_asked.any() and not torch.equal(grid.occupancy, grid.gate())
    ref = grid.occupied(o[:, None, :] + s[..., None] * d[:, None, :],
                        t[:, None, :].expand(n, k, 1))
    assert torch.equal(grid.occupied_rays(o, d, t, s), ref)
    assert 0 < ref.float().mean() < 0.5


@pytest.mark.parametrize(("key", "bad"), [("refine", [2]), ("refine", [0, 2]),
                                          ("refine", "24"), ("refine_dilation", [1, -1]),
                                          ("refine_budget", 0), ("refine_budget", 1.5),
                                          ("refine_below", 0), ("refine_below", 1.5)])
def test_a_bad_refinement_is_one_error_naming_the_key(key: str, bad) -> None:
    cfg = {"refine": [2, 2], key: bad}
    with pytest.raises(InputError, match=rf"render\.occupancy\.{key}"):
        build_grid([-1, -1, -1], [1, 1, 1], **cfg)


def test_without_refine_the_grid_is_the_plain_one() -> None:
    g = build_grid([-1, -1, -1], [1, 1, 1], resolution=4, refine=None, refine_budget=7)
    assert type(g) is OccupancyGrid
