"""HexPlane's fused rank sum of three plane · plane · line products (baselines.hex_fused):
the factors' gradients equal sampling factor by factor, to the bit; the values agree to
rounding and with an independent fp64 reference; both space-time layouts; a non-finite
coordinate and a corner outside a plane; the halves' gradients summed on two threads;
the cases it leaves to the factor-by-factor path."""

from __future__ import annotations

import pytest
import torch
from fused_pairs import fused_and_by_factor, split_between_two_threads

import baselines.hex_fused as hex_fused
import baselines.hexplane as hexplane
from baselines import HexPlaneField
from baselines.factorised import FEATURES, FactorisedField
from baselines.grids import sample_grid_reference
from baselines.hex_fused import hex_rank_sum, supported
from eventrecon.errors import InputError
from eventrecon.sim.jit import GRAIN, numba_threads
from eventrecon.sim.pipeline import torch_threads


def _field(resolution=(9, 8, 8, 5), layout="authors", rank=3, dtype=torch.float32,
           seed=0) -> HexPlaneField:
    """A field whose factors are O(1) (the initial N(0, 1/R²) products are tiny)."""
    f = HexPlaneField(rank=rank, resolution=(resolution[0],) * 3 + (resolution[3],),
                      spacetime_layout=layout, seed=seed).to(dtype)
    g = torch.Generator().manual_seed(seed + 7)
    with torch.no_grad():
        for p in f.grids.factors:
            p.copy_(torch.randn(p.shape, generator=g, dtype=dtype))
    return f


def _coords(n: int, dtype: torch.dtype, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    c = torch.rand(n, 4, generator=g, dtype=dtype) * 2.4 - 1.2       # some outside [-1, 1]
    c[:2] = torch.tensor([[-1.0] * 4, [1.0] * 4], dtype=dtype)        # the edges
    return c


def _fused(f: HexPlaneField, coords: torch.Tensor, features: int = FEATURES):
    g = f.grids
    return hex_rank_sum(g.leading(f.channels(features)), g.axes, coords, g.align_corners,
                        g.padding, f.rank)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("layout", ["authors", "swapped"])
@pytest.mark.parametrize("padding", ["zeros", "border"])
def test_gradients_equal_factor_by_factor_and_values_agree(dtype, layout, padding):
    f = _field(layout=layout, dtype=dtype)
    f.grids.padding = padding
    coords = _coords(900, dtype)
    w = torch.randn(900, FEATURES, generator=torch.Generator().manual_seed(2), dtype=dtype)
    params = list(f.grids.factors)
    with torch_threads(1):
        fused = _fused(f, coords)
        g_fused = torch.autograd.grad((fused * w).sum(), params)
        ref = FactorisedField.rank_sum(f, coords)               # sample, combine, Tensor.sum
        g_ref = torch.autograd.grad((ref * w).sum(), params)
    assert fused is not None and fused.shape == (900, FEATURES)
    for a, b in zip(g_fused, g_ref):
        assert torch.equal(a, b)                                # the same sums, in order
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    assert torch.allclose(fused, ref, rtol=tol, atol=tol)
    # an independent reference: the explicit corner gathers, in float64
    s = [sample_grid_reference(p.double(), coords[:, list(ax)].double(), ac, padding).t()
         for p, ax, ac in zip(params, f.grids.axes, f.grids.align_corners)]
    exact = sum(s[k] * s[k + 3] * s[k + 6] for k in range(3))
    exact = exact.reshape(-1, FEATURES, f.rank).sum(-1)
    assert (fused.double() - exact).abs().max().item() <= 10 * tol * max(1.0, exact.abs().max())
    with torch.no_grad():                                       # no graph: the same
        assert torch.equal(_fused(f, coords), fused.detach())


def test_density_only_reads_the_leading_channels_and_its_gradient_reaches_them_only():
    f = _field(rank=4)
    coords = _coords(300, torch.float32)
    params = list(f.grids.factors)
    with torch_threads(1):
        fused = _fused(f, coords, features=1)
        g = torch.autograd.grad(fused.sum(), params)
        ref = FactorisedField.rank_sum(f, coords, features=1)
        g_ref = torch.autograd.grad(ref.sum(), params)
    assert fused.shape == (300, 1) and torch.allclose(fused, ref, rtol=1e-5, atol=1e-5)
    for a, b in zip(g, g_ref):
        assert torch.equal(a, b) and a[4:].abs().sum() == 0 and a[:4].abs().sum() > 0


def test_a_non_finite_coordinate_reads_nan_and_a_corner_outside_is_not_read():
    """A point below the grid's lower edge has its lower corner at vertex −1, outside: it
    must read vertex 0 only, not wrap round to the last row (made non-finite here, a
    diverged parameter); NaN and inf coordinates read NaN; the gradients, NaN included,
    are the factor-by-factor path's."""
    f = _field()
    coords = _coords(60, torch.float32)
    coords[7, 2], coords[9, 3] = float("nan"), float("inf")
    with torch.no_grad():                       # P_xy reads y along its first grid axis
        f.grids.factors[0][:, -1, :] = float("inf")
    coords[11] = torch.tensor([0.0, -1.05, 0.0, 0.0])           # y below the lower edge
    coords[12] = torch.tensor([0.0, 1.0, 0.0, 0.0])             # on the last row
    params = list(f.grids.factors)
    with torch_threads(1):
        fused = _fused(f, coords)
        g = torch.autograd.grad(fused[:11].sum(), params)
        ref = FactorisedField.rank_sum(f, coords)
        g_ref = torch.autograd.grad(ref[:11].sum(), params)
    assert fused[7].isnan().all() and fused[9].isnan().all()
    assert torch.equal(fused.isnan(), ref.isnan())
    assert torch.isfinite(fused[11]).all() and not torch.isfinite(fused[12]).all()
    for a, b in zip(g, g_ref):
        torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True)
    empty = _fused(f, coords[:0])
    assert empty.shape == (0, FEATURES)
    assert all(g.abs().sum() == 0 for g in torch.autograd.grad(empty.sum(), params))


def test_the_cases_left_to_the_factor_by_factor_path(monkeypatch):
    f = _field()
    g, coords = f.grids, _coords(10, torch.float32)
    factors = g.leading(None)
    assert supported(factors, g.axes, coords, g.align_corners)
    assert hex_rank_sum(factors, g.axes, coords.double(), g.align_corners, "zeros", 3) is None
    assert hex_rank_sum(factors, g.axes, coords.requires_grad_(True), g.align_corners,
                        "zeros", 3) is None                     # coordinates with a gradient
    coords = coords.detach()
    assert hex_rank_sum(factors[:8], g.axes[:8], coords, g.align_corners[:8], "zeros",
                        3) is None                              # eight factors
    mixed = [True] * 5 + [False] * 4                            # planes of two conventions
    assert hex_rank_sum(factors, g.axes, coords, mixed, "zeros", 3) is None
    assert not supported([p.to("meta") for p in factors], g.axes, coords, g.align_corners)
    assert hex_rank_sum(factors, g.axes, coords[:, :3], g.align_corners, "zeros", 3) is None
    with monkeypatch.context() as m:                             # too large to stay in cache
        m.setattr(hex_fused, "MAX_BYTES", sum(f.numel() * 4 for f in factors) - 4)
        assert hex_rank_sum(factors, g.axes, coords, g.align_corners, "zeros", 3) is None
    assert hex_rank_sum(factors, g.axes, coords, g.align_corners, "zeros", 3) is not None
    paper = [torch.empty(32, 500, 500)] * 3 + [torch.empty(32, 500, 24)] * 3 \
        + [torch.empty(32, 500)] * 3                                # the authors' size
    assert not supported(paper, g.axes, coords, g.align_corners)
    assert not supported(factors, [*g.axes[:8], (0, 1)], coords, g.align_corners)  # a line of 2
    with pytest.raises(InputError, match="rank: expected a divisor of the factors' 12 channels"):
        hex_rank_sum(factors, g.axes, coords, g.align_corners, "zeros", 5)


def test_the_hexplane_field_fused_equals_the_field_factor_by_factor(monkeypatch):
    field = _field(resolution=(10, 10, 10, 6), rank=4)
    out = fused_and_by_factor(field, hexplane, "hex_rank_sum", monkeypatch, n=400)
    (s1, c1, g1), (s2, c2, g2) = out
    assert torch.allclose(s1, s2, rtol=1e-5) and torch.allclose(c1, c2, rtol=1e-5, atol=1e-7)
    for a, b in zip(g1, g2):
        assert torch.equal(a, b)


@pytest.mark.skipif(numba_threads() < 2, reason="numba has one thread here")
def test_split_between_two_threads_same_values_and_the_halves_gradients_summed(monkeypatch):
    """With two torch threads the points run as two ranges on numba's threads: the same
    values to the bit, and the factors' gradients exactly the sum of each half's
    one-thread gradient (the ranges scatter into their own copies, added once)."""
    n = 4 * GRAIN
    f = _field(resolution=(16, 16, 16, 8), rank=4)
    counts = split_between_two_threads(hex_fused, lambda c: _fused(f, c),
                                       list(f.grids.factors), _coords(n, torch.float32),
                                       monkeypatch)
    assert counts == {"_forward_parts": 2, "_backward_parts": 1}
