"""Empty-space skipping: the occupancy grid, its updates, and renders with and without it."""

from __future__ import annotations

import pytest
import torch
from omegaconf import OmegaConf
from torch import Tensor, nn

from baselines import HexPlaneField
from eventrecon.common.errors import InputError
from eventrecon.fields.base import Field
from eventrecon.render.occupancy import OccupancyGrid
from eventrecon.render.volume import VolumeRenderer

CYL = {"radius": 0.5, "y_min": -0.75, "y_max": 0.25}


class Blob(Field):
    """A moving blob with exactly zero density outside it:
    ``σ = k · relu(r² − |x − c(t)|²)``, ``c(t) = (0.3 (2t − 1), −0.25, 0)``, constant colour;
    ``k`` and the colour are parameters (gradients can be compared)."""

    def __init__(self, k: float = 400.0, radius: float = 0.15):
        super().__init__()
        self.k = nn.Parameter(torch.tensor(float(k)))
        self.colour = nn.Parameter(torch.tensor([0.2, 0.6, 0.9]))
        self.radius = radius

    def forward(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        c = torch.cat([0.3 * (2 * t - 1), torch.full_like(t, -0.25), torch.zeros_like(t)], -1)
        d2 = (xyz - c).square().sum(-1)
        sigma = self.k * torch.relu(self.radius**2 - d2)
        return sigma, self.colour.expand(xyz.shape[0], 3)


def _rays(n: int, seed: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Rays from a ring at radius 2.5 looking at the cylinder, random times."""
    g = torch.Generator().manual_seed(seed)
    ang = torch.rand(n, generator=g) * 6.2832
    o = torch.stack([2.5 * ang.cos(), torch.full((n,), -0.25), 2.5 * ang.sin()], -1)
    target = torch.stack([torch.rand(n, generator=g) - 0.5, torch.rand(n, generator=g) * 0.8
                          - 0.65, torch.rand(n, generator=g) - 0.5], -1) * 0.8
    d = target - o
    return o, d / d.norm(dim=-1, keepdim=True), torch.rand(n, 1, generator=g), torch.full(
        (n, 3), 0.35)


def _with_grid(field: Field, **grid) -> VolumeRenderer:
    r = VolumeRenderer(n_coarse=32, n_fine=32, skip="grid", occupancy=grid, **CYL)
    for step in range(3):
        r.occupancy.update(lambda x, t: r.masked_density(field, x, t),
                           torch.Generator().manual_seed(step))
    return r


def test_unasked_grid_skips_nothing_and_the_render_equals_the_dense_one():
    field = Blob()
    dense = VolumeRenderer(n_coarse=32, n_fine=32, **CYL)
    fresh = VolumeRenderer(n_coarse=32, n_fine=32, skip="grid", **CYL)
    assert fresh.occupancy.occupied_fraction() == 1.0
    o, d, t, bg = _rays(300, 0)
    a = dense.render_rays(field, o, d, t, bg)[-1]["rgb"]
    b = fresh.render_rays(field, o, d, t, bg)[-1]["rgb"]
    assert (a - b).abs().max().item() <= 2e-4  # only the transmittance stop differs


@pytest.mark.parametrize(("recheck", "time_bins", "dilation"),
                         [(1.0, 8, (1, 1)), (0.25, 8, (1, 1)), (0.25, 16, (1, 0))])
def test_no_sample_above_the_threshold_is_skipped(recheck: float, time_bins: int,
                                                  dilation: tuple[int, int]):
    """Against a dense reference: every point whose density exceeds the threshold lies in
    an occupied cell (random points over the box and times), also when only a share of
    the occupied cells is re-asked at each update, and without dilation in time where the
    blob moves less than a cell per bin (0.6 / 16 against cells 1/24 of the box)."""
    field = Blob()
    r = _with_grid(field, resolution=24, time_bins=time_bins, threshold=0.05, fraction=1.0,
                   recheck=recheck, dilation=dilation)
    g = torch.Generator().manual_seed(9)
    lo, hi = r.occupancy.lo, r.occupancy.hi
    x = lo + torch.rand(400_000, 3, generator=g) * (hi - lo)
    t = torch.rand(400_000, 1, generator=g)
    dens = r.masked_density(field, x, t)
    above = dens > 0.05
    assert above.sum() > 1000  # the test sees the blob
    assert bool(r.occupancy.occupied(x, t)[above].all())
    assert r.occupancy.occupied_fraction() < 0.3  # and the grid skips most of the box


@pytest.mark.parametrize("groups", [1, 4])
def test_skipped_render_equals_dense_and_kept_gradients_are_identical(groups: int):
    """A field with exactly zero density where cells are empty, densities too low to stop a
    ray: the skipped render is the dense one, and so are the gradients, with the coarse
    samples marched in one group or in four."""
    dense_field, skip_field = Blob(k=20.0), Blob(k=20.0)
    r_skip = _with_grid(skip_field, resolution=32, time_bins=8, threshold=1e-6)
    r_skip.march_chunks = groups
    r_dense = VolumeRenderer(n_coarse=32, n_fine=32, **CYL)
    o, d, t, bg = _rays(400, 1)
    gen = (torch.Generator().manual_seed(5), torch.Generator().manual_seed(5))
    out_d = r_dense.render_rays(dense_field, o, d, t, bg, perturb=True, gen=gen[0])
    out_s = r_skip.render_rays(skip_field, o, d, t, bg, perturb=True, gen=gen[1])
    for a, b in zip(out_d, out_s):
        assert torch.allclose(a["rgb"], b["rgb"], atol=1e-6)
        assert torch.allclose(a["opacity"], b["opacity"], atol=1e-6)
    loss_d = sum((lv["rgb"] - 0.5).square().mean() for lv in out_d)
    loss_s = sum((lv["rgb"] - 0.5).square().mean() for lv in out_s)
    loss_d.backward()
    loss_s.backward()
    assert torch.allclose(dense_field.k.grad, skip_field.k.grad, rtol=1e-5)
    assert torch.allclose(dense_field.colour.grad, skip_field.colour.grad, rtol=1e-5)


def _fit_hexplane(steps: int = 150) -> HexPlaneField:
    """A tiny HexPlane trained on the blob's density (σ = exp(raw) is never exactly 0)."""
    torch.manual_seed(0)
    f = HexPlaneField(rank=4, resolution=(24, 24, 24, 8))
    r = VolumeRenderer(**CYL)
    f.set_scene_box(*r.cylinder.box())
    target = Blob()
    opt = torch.optim.Adam(f.parameters(), lr=3e-2)
    g = torch.Generator().manual_seed(1)
    lo, hi = torch.tensor([-0.5, -0.75, -0.5]), torch.tensor([0.5, 0.25, 0.5])
    for _ in range(steps):
        x = lo + torch.rand(4096, 3, generator=g) * (hi - lo)
        t = torch.rand(4096, 1, generator=g)
        sigma, rgb = f(x, t)
        ts, tc = target(x, t)
        loss = (torch.log1p(sigma) - torch.log1p(ts)).square().mean() + (rgb - tc).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return f


def test_trained_field_renders_agree_within_1e3_with_a_conservative_grid():
    f = _fit_hexplane()
    dense = VolumeRenderer(n_coarse=32, n_fine=32, **CYL)
    skip = _with_grid(f, resolution=32, time_bins=8, threshold=1e-3)
    assert skip.occupancy.occupied_fraction() < 0.9  # something is skipped
    o, d, t, bg = _rays(500, 2)
    with torch.no_grad():
        a = dense.render_rays(f, o, d, t, bg)[-1]["rgb"]
        b = skip.render_rays(f, o, d, t, bg)[-1]["rgb"]
    assert (a - b).abs().max().item() <= 1e-3


def test_fewer_samples_reach_the_field_and_the_grid_resumes_exactly():
    field = Blob()
    r = _with_grid(field, resolution=32, time_bins=8, threshold=0.01)
    seen: list[int] = []
    hook = field.register_forward_hook(lambda m, inp, out: seen.append(inp[0].shape[0]))
    o, d, t, bg = _rays(500, 3)
    r.render_rays(field, o, d, t, bg, perturb=True, gen=torch.Generator().manual_seed(0))
    hook.remove()
    per_ray = sum(seen) / 500
    assert per_ray < 0.25 * (32 + 32)
    # the grid is state: saved and restored exactly, and a further update is the same
    state = {k: v.clone() for k, v in r.state_dict().items()}
    again = VolumeRenderer(n_coarse=32, n_fine=32, skip="grid", occupancy={"resolution": 32,
                     "time_bins": 8, "threshold": 0.01}, **CYL)
    again.load_state_dict(state)
    assert torch.equal(again.occupancy.occupancy, r.occupancy.occupancy)
    for rr in (r, again):
        rr.occupancy.update(lambda x, tt, rr=rr: rr.masked_density(field, x, tt),
                            torch.Generator().manual_seed(42))
    assert torch.equal(again.occupancy.density, r.occupancy.density)


def test_training_marches_in_one_field_call_with_the_image_march_stops_as_masks():
    """Under autograd the occupied coarse samples reach the field in one call and the
    march's stops are masks; without it the groups are separate calls. Rays that become
    opaque stop, and both renders (values, and which samples count) are the same."""
    field = Blob(k=5000.0, radius=0.35)         # opaque: σ up to 600 per unit
    r = _with_grid(field, resolution=32, time_bins=8, threshold=0.01)
    r.query_buckets = 0                          # exact row counts
    assert r.march_chunks == 4
    calls: list[int] = []
    hook = field.register_forward_hook(lambda m, inp, out: calls.append(inp[0].shape[0]))
    o, d, t, bg = _rays(300, 4)
    trained = r.render_rays(field, o, d, t, bg)
    n_train, rows_train = len(calls), sum(calls)
    calls.clear()
    with torch.no_grad():
        image = r.render_rays(field, o, d, t, bg)
    hook.remove()
    assert (n_train, len(calls)) == (2, 5)       # coarse call(s) + the fine level
    assert rows_train > sum(calls)               # samples behind a stop: evaluated, masked
    assert float(image[0]["opacity"].max()) > 1 - 1e-4      # some rays do stop
    for a, b in zip(trained, image):
        assert torch.allclose(a["rgb"].detach(), b["rgb"], atol=1e-6)
        assert torch.equal(a["weights"].detach() > 0, b["weights"] > 0)


def test_grid_marks_outside_the_cylinder_empty():
    g = OccupancyGrid([-0.5, -0.75, -0.5], [0.5, 0.25, 0.5], resolution=16, time_bins=2)
    r = VolumeRenderer(**CYL)

    class Fog(Field):
        def forward(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
            return torch.ones(xyz.shape[0]), torch.ones(xyz.shape[0], 3)

    g.update(lambda x, t: r.masked_density(Fog(), x, t), torch.Generator().manual_seed(0))
    # the box corners lie outside the cylinder x² + z² <= 0.25 (and their neighbours too)
    corner = torch.tensor([[0.49, -0.25, 0.49], [-0.49, -0.7, -0.49]])
    centre = torch.tensor([[0.0, -0.25, 0.0]])
    assert not g.occupied(corner, torch.zeros(2, 1)).any()
    assert g.occupied(centre, torch.zeros(1, 1)).all()


def test_grid_queries_ask_the_density_alone_in_blocks_under_the_image_dtype():
    """The grid's field queries run as images do: ``density_only`` in blocks of at most
    ``query_rows`` (the last one padded to a repeated size), fp32 out, and under the run's
    image dtype (bf16 here, where the CPU has it natively) within bf16's rounding."""
    from eventrecon.fields import NeRFField
    from eventrecon.render.renderer import image_autocast

    torch.manual_seed(0)
    field = NeRFField(depth=2, width=32, skip=-1, pos_bands=4, time_bands=2, remap_width=32,
                      colour_width=16, anneal_steps=0)
    r = VolumeRenderer(n_coarse=8, n_fine=8, skip="grid", query_rows=1000, **CYL)
    g = torch.Generator().manual_seed(1)
    x, t = torch.rand(4200, 3, generator=g) - 0.5, torch.rand(4200, 1, generator=g)
    rows: list[int] = []
    alone = field.density_only
    field.density_only = lambda a, b: (rows.append(a.shape[0]), alone(a, b))[1]
    with torch.no_grad():
        reference = field(x, t)[0] * r.cylinder.inside(x, 1.0, tol=1e-5)
        fp32 = r.masked_density(field, x, t)
        r.image_dtype = torch.bfloat16
        bf16 = r.masked_density(field, x, t)
    assert rows == [1000] * 4 + [256] + [1000] * 4 + [256]     # 200 rows padded to 256
    assert fp32.dtype == bf16.dtype == torch.float32
    assert torch.allclose(fp32, reference, rtol=1e-5, atol=1e-7)
    if isinstance(image_autocast(torch.bfloat16, "cpu"), torch.autocast):
        assert not torch.equal(bf16, fp32)                          # it ran in bf16
    rel = ((bf16 - fp32).abs() / fp32.clamp_min(1e-2)).max()
    assert float(rel) < 0.05 and float(fp32.max()) > 0.1


def test_a_fog_below_the_threshold_keeps_its_denser_half_instead_of_emptying_the_grid():
    grid = OccupancyGrid([-1, -1, -1], [1, 1, 1], resolution=4, time_bins=1, threshold=0.01)
    # a thin fog: σ = 0.004 for x < 0, 0.006 for x > 0, everywhere under the threshold 0.01;
    # the mean over the 64 asked cells is 0.005, so τ = 0.005 and only the x > 0 half (and
    # its dilation by one cell, x ∈ [-0.5, 0]) stays occupied
    assert grid.update(lambda x, t: 0.004 + 0.002 * (x[:, 0] > 0).float(),
                       torch.Generator().manual_seed(0)) == 64
    assert float(grid.effective_threshold()) == pytest.approx(0.005)
    probe = torch.tensor([[-0.9, 0.0, 0.0], [-0.2, 0.0, 0.0], [0.9, 0.0, 0.0]])
    assert grid.occupied(probe, torch.zeros(3, 1)).tolist() == [False, True, True]
    assert grid.occupied_fraction() == pytest.approx(0.75)
    # a field denser than the threshold somewhere keeps the configured threshold
    grid.update(lambda x, t: 5.0 * (x[:, 0] > 0.5).float(), torch.Generator().manual_seed(1))
    assert float(grid.effective_threshold()) == pytest.approx(0.01)


def test_rechecking_a_share_of_the_occupied_cells_costs_that_share_and_forgets_at_the_same_rate():
    """While nearly every cell is above the threshold an update asks about ``recheck`` of
    them; a cell the field leaves empties after about as many updates as with
    ``recheck = 1`` (γ per update: 90 updates from σ = 1 to the threshold 0.01)."""
    def half(x: Tensor, t: Tensor) -> Tensor:     # σ = 1 on x > 0
        return (x[:, 0] > 0).float()

    def quarter(x: Tensor, t: Tensor) -> Tensor:  # the field leaves 0 < x < 0.5
        return (x[:, 0] > 0.5).float()

    slab = torch.tensor([[0.1, y, z] for y in (-0.9, -0.3, 0.3, 0.9) for z in (-0.9, 0.0, 0.9)])
    emptied = {}
    for recheck in (1.0, 0.25):
        grid = OccupancyGrid([-1, -1, -1], [1, 1, 1], resolution=8, time_bins=1,
                             threshold=0.01, fraction=0.25, recheck=recheck)
        grid.update(half, torch.Generator().manual_seed(0))
        asked = [grid.update(half, torch.Generator().manual_seed(s)) for s in range(1, 41)]
        dense = int(grid._dense().sum())     # 256 cells with x > 0
        empty = 512 - dense
        assert dense == 256
        expect = recheck * dense + 0.25 * empty
        assert abs(sum(asked) / 40 - expect) < 4 * (expect / 40) ** 0.5 + 1
        for k in range(1, 400):
            grid.update(quarter, torch.Generator().manual_seed(100 + k))
            if not grid.occupied(slab, torch.zeros(len(slab), 1)).any():
                emptied[recheck] = k
                break
    assert emptied[1.0] == 90
    assert 60 <= emptied[0.25] <= 180


@pytest.mark.parametrize("dilation", [(0, 0), (1, 0), (0, 1), (1, 1), (2, 1), (1, 3), (1, 9)])
def test_dilation_widens_occupancy_by_its_cells_in_space_and_bins_in_time(dilation):
    """One dense cell: the occupied cells are exactly those within ``s`` cells of it in
    every axis and ``b`` bins in time (an independent reference from the indices)."""
    s, b = dilation
    g = OccupancyGrid([-1, -1, -1], [1, 1, 1], resolution=8, time_bins=5, threshold=0.5,
                      dilation=dilation)
    g.asked.fill_(True)
    g.density[3, 1, 6, 4] = 1.0
    g.refresh()
    idx = torch.stack(torch.meshgrid(*(torch.arange(n) for n in g.occ.shape), indexing="ij"))
    far = (idx - torch.tensor([3, 1, 6, 4])[:, None, None, None, None]).abs()
    expected = (far[0] <= b) & (far[1:] <= s).all(0)
    assert torch.equal(g.occ, expected)
    # counted by hand: (2, 1) is cut by the box's faces, (1, 3) by the last of the 5 bins,
    # (1, 9) by both ends (both reach all 5)
    assert int(g.occ.sum()) == {(0, 0): 1, (1, 0): 27, (0, 1): 3, (1, 1): 81,
                                (2, 1): 3 * 4 * 4 * 5, (1, 3): 5 * 27, (1, 9): 5 * 27}[dilation]


def test_one_time_bin_is_widened_in_space_only():
    g = OccupancyGrid([-1, -1, -1], [1, 1, 1], resolution=8, time_bins=1, threshold=0.5,
                      dilation=OmegaConf.create([1, 2]))       # a list as Hydra passes it
    assert g.dilation == (1, 2)
    g.asked.fill_(True)
    g.density[0, 1, 6, 4] = 1.0
    g.refresh()
    assert int(g.occ.sum()) == 27


@pytest.mark.parametrize("bad", [[1], [1, -1], [1.5, 0], "11", b"\x01\x00", [True, 0]])
def test_a_bad_dilation_is_one_error_naming_the_key(bad):
    with pytest.raises(InputError, match=r"render\.occupancy\.dilation.*two integers"):
        OccupancyGrid([-1, -1, -1], [1, 1, 1], dilation=bad)
