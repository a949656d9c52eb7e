"""The compiled occupancy lookup along rays gives PyTorch's mask, sample for sample."""

from __future__ import annotations

import pytest
import torch

from eventrecon.render import occupancy_lookup
from eventrecon.render.occupancy import OccupancyGrid

pytestmark = pytest.mark.skipif(not occupancy_lookup.AVAILABLE, reason="needs numba")


def _grid(seed: int, resolution: int = 8, time_bins: int = 4,
          lo=(-0.5, -0.75, -0.5), hi=(0.5, 0.25, 0.5)) -> OccupancyGrid:
    """A grid over a box (default: the default cylinder's) with a random occupancy."""
    grid = OccupancyGrid(list(lo), list(hi), resolution=resolution, time_bins=time_bins)
    g = torch.Generator().manual_seed(seed)
    grid.occ.copy_(torch.rand(grid.occ.shape, generator=g) < 0.4)
    return grid


def _reference(grid: OccupancyGrid, o, d, t, s) -> torch.Tensor:
    """PyTorch's path: the points stored, then :meth:`OccupancyGrid.occupied`."""
    n, k = s.shape
    return grid.occupied(o[:, None, :] + s[..., None] * d[:, None, :],
                         t[:, None, :].expand(n, k, 1))


def _check(grid: OccupancyGrid, o, d, t, s) -> torch.Tensor:
    """The compiled mask, asserted to be served by the compiled loop and equal to PyTorch's."""
    assert occupancy_lookup.supported(o, d, t, s, grid.lo, grid.hi, grid.occupancy)
    got = grid.occupied_rays(o, d, t, s)
    assert torch.equal(got, _reference(grid, o, d, t, s))
    return got


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_random_rays_get_the_same_mask_as_the_stored_points(dtype) -> None:
    """Rays from around the box through it (about half their samples outside), at
    times inside and outside ``[0, 1]``: the same mask, in float32 and float64."""
    grid = _grid(0)
    g = torch.Generator().manual_seed(1)
    n, k = 500, 37
    o = (torch.randn(n, 3, generator=g) * 1.5).to(dtype)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g) * 0.3 - o.float(),
                                      dim=-1).to(dtype)
    s = torch.sort(torch.rand(n, k, generator=g) * 4, -1).values.to(dtype)
    t = torch.rand(n, 1, generator=g) * 1.4 - 0.2
    got = _check(grid, o, d, t, s)
    assert 0.05 < got.float().mean() < 0.5          # both values occur, not a trivial mask


@pytest.mark.parametrize("resolution", [8, 24, 32, 48])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_samples_within_ulps_of_every_cell_boundary_get_pytorchs_cells(resolution, dtype):
    """On an uneven box, with resolutions whose ``u·G`` is rounded (24, 48) or exact (8,
    32): rays aimed so that ``o + s d`` lands within a few ulps of a cell boundary on
    each axis, through real arithmetic. Any other order of the operations, a fused
    multiply-add or ``u·G`` in another precision moves some of them to the next cell."""
    grid = _grid(resolution, resolution, 4, lo=(-0.31, -0.7, -0.3), hi=(0.3, 0.13, 0.29))
    g = torch.Generator().manual_seed(resolution)
    n, k = 400, 8
    lo, span = grid.lo.double(), (grid.hi - grid.lo).to(dtype).double()
    bounds = lo + (torch.arange(resolution + 1, dtype=torch.float64) / resolution)[:, None] * span
    p = bounds[torch.randint(resolution + 1, (n, 3), generator=g), torch.arange(3)].to(dtype)
    for _ in range(2):                               # up to two ulps either way
        away = torch.randn(p.shape, generator=g, dtype=torch.float64).to(dtype)
        p = torch.where(torch.rand(p.shape, generator=g) < 0.5, p, torch.nextafter(p, away))
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64),
                                      dim=-1).to(dtype)
    s = (torch.rand(n, k, generator=g, dtype=torch.float64) * 3).to(dtype)
    o = (p.double() - s[:, :1].double() * d.double()).to(dtype)     # sample 0 near p
    s[:, 1:] = s[:, :1] + (torch.randint(-2, 3, (n, k - 1), generator=g) * 1e-7).to(dtype)
    _check(grid, o, d, torch.rand(n, 1, generator=g), s)


def test_a_product_rounded_up_to_a_cell_boundary_takes_the_upper_cell():
    """``u = 0.45833331``: ``24 u`` is just below 11, but rounds to 11 in float32, as
    PyTorch computes it; so the sample is in cell 11 (a float64 product gave cell 10)."""
    grid = OccupancyGrid([0, 0, 0], [1, 1, 1], resolution=24, time_bins=1)
    grid.occ.zero_()
    grid.occ[0, 11] = True
    o, d = torch.tensor([[0.4583333134651184, 0.5, 0.5]]), torch.tensor([[1.0, 0.0, 0.0]])
    got = _check(grid, o, d, torch.zeros(1, 1), torch.zeros(1, 1))
    assert got.tolist() == [[True]]


def test_faces_and_non_finite_inputs_match() -> None:
    """Samples on the box's faces and corners, NaN and infinite coordinates, and times
    NaN, ±inf, huge, 0 and 1 (their bins are PyTorch's own on any platform)."""
    grid = _grid(2)
    lo, hi = grid.lo, grid.hi
    ticks = torch.linspace(0, 1, 9)                  # u = i/8: every cell boundary
    o = torch.cat([lo + ticks[:, None] * (hi - lo), lo[None], hi[None],
                   torch.tensor([[float("nan"), 0.0, 0.0]])])
    n = o.shape[0]
    d = torch.zeros(n, 3)
    d[:, 0] = 1.0
    steps = [0.0, 1 / 8, -1 / 8, 0.5, float("nan"), float("inf"), 1e30, -0.0]
    s = torch.tensor(steps).expand(n, len(steps)).contiguous()
    times = torch.tensor([0.0, 1.0, 0.999999, 0.25, float("nan"), float("inf"),
                          -float("inf"), 1e30, -1e30, 2.0, -0.5, 0.5])[:n, None]
    got = _check(grid, o, d, times, s)
    assert not got[-1].any()                         # a NaN origin is outside everywhere


def test_unsupported_inputs_take_pytorchs_path() -> None:
    """Mixed dtypes, a grid off the CPU or of the wrong shape are not the compiled loop's:
    it declines, and the grid falls back with PyTorch's mask."""
    grid = _grid(3)
    g = torch.Generator().manual_seed(4)
    o, d = torch.randn(20, 3, generator=g).double(), torch.randn(20, 3, generator=g)
    s, t = torch.rand(20, 5, generator=g), torch.rand(20, 1, generator=g)
    lo, hi, occ = grid.lo, grid.hi, grid.occupancy
    assert not occupancy_lookup.supported(o, d, t, s, lo, hi, occ)
    assert occupancy_lookup.lookup_rays(o, d, t, s, lo, hi, occ) is None
    assert torch.equal(grid.occupied_rays(o, d, t, s), _reference(grid, o, d, t, s))
    o = o.float()
    assert occupancy_lookup.supported(o, d, t, s, lo, hi, occ)
    assert not occupancy_lookup.supported(o, d, t, s, lo, hi, occ.to("meta"))
    assert not occupancy_lookup.supported(o, d, t, s, lo, hi, occ[:, :, :4])
    assert not occupancy_lookup.supported(o, d, t, s, lo[:2], hi, occ)
