"""The compiled occupancy lookup along rays gives PyTorch's mask, sample for sample."""

from __future__ import annotations

import pytest
import torch

from eventrecon.render import occupancy_lookup
from eventrecon.render.occupancy import OccupancyGrid

pytestmark = pytest.mark.skipif(not occupancy_lookup.AVAILABLE, reason="needs numba")


def _grid(seed: int, resolution: int = 8, time_bins: int = 4) -> OccupancyGrid:
    """A grid over the default cylinder's box with a random occupancy."""
    grid = OccupancyGrid([-0.5, -0.75, -0.5], [0.5, 0.25, 0.5], resolution=resolution,
                         time_bins=time_bins)
    g = torch.Generator().manual_seed(seed)
    grid.occ.copy_(torch.rand(grid.occ.shape, generator=g) < 0.4)
    return grid


def _reference(grid: OccupancyGrid, o, d, t, s) -> torch.Tensor:
    """PyTorch's path: the points stored, then :meth:`OccupancyGrid.occupied`."""
    n, k = s.shape
    return grid.occupied(o[:, None, :] + s[..., None] * d[:, None, :],
                         t[:, None, :].expand(n, k, 1))


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
    got = grid.occupied_rays(o, d, t, s)
    assert occupancy_lookup.supported(o, d, t, s, grid.occupancy)
    want = _reference(grid, o, d, t, s)
    assert torch.equal(got, want)
    assert 0.05 < got.float().mean() < 0.5          # both values occur, not a trivial mask


def test_faces_cell_boundaries_and_non_finite_inputs_match() -> None:
    """Samples exactly on the box's faces and corners and on cell boundaries (``u·G``
    an integer), NaN and infinite coordinates, and times NaN, ±inf, huge, 0 and 1: the
    compiled loop takes PyTorch's cells (x86's conversion of an undefined time included)."""
    grid = _grid(2)
    lo, hi = grid.lo, grid.hi
    ticks = torch.linspace(0, 1, 9)                  # u = i/8: every cell boundary
    grid_pts = lo + ticks[:, None] * (hi - lo)       # [9, 3] on the diagonal
    o = torch.cat([grid_pts, lo[None], hi[None], torch.tensor([[float("nan"), 0.0, 0.0]])])
    n = o.shape[0]
    d = torch.zeros(n, 3)
    d[:, 0] = 1.0
    steps = [0.0, 1 / 8, -1 / 8, 0.5, float("nan"), float("inf"), 1e30, -0.0]
    s = torch.tensor(steps).expand(n, len(steps)).contiguous()
    times = torch.tensor([0.0, 1.0, 0.999999, 0.25, float("nan"), float("inf"),
                          -float("inf"), 1e30, -1e30, 2.0, -0.5, 0.5])[:n, None]
    got = grid.occupied_rays(o, d, times, s)
    assert torch.equal(got, _reference(grid, o, d, times, s))
    assert not got[-1].any()                         # a NaN origin is outside everywhere


def test_unsupported_inputs_take_pytorchs_path() -> None:
    """Mixed dtypes are not the compiled loop's: the grid falls back with the same mask."""
    grid = _grid(3)
    g = torch.Generator().manual_seed(4)
    o, d = torch.randn(20, 3, generator=g).double(), torch.randn(20, 3, generator=g)
    s, t = torch.rand(20, 5, generator=g), torch.rand(20, 1, generator=g)
    assert not occupancy_lookup.supported(o, d, t, s, grid.occupancy)
    assert occupancy_lookup.lookup_rays(o, d, t, s, grid.lo, grid.hi, grid.occupancy) is None
    assert torch.equal(grid.occupied_rays(o, d, t, s), _reference(grid, o, d, t, s))
