"""TensoRF-CP's fused rank sum of four line products (baselines.cp_fused): the same
gradients as sampling line by line, to the bit; values to rounding, and against an
independent fp64 reference; split between two threads, the halves' gradients summed;
the cases it leaves to the line-by-line path."""

from __future__ import annotations

import pytest
import torch
from fused_pairs import fused_and_by_factor, split_between_two_threads

import baselines.tensorf_cp as tensorf_cp
from baselines import TensoRFCPField
from baselines.cp_fused import cp_rank_sum, supported
from baselines.factorised import FEATURES
from baselines.grids import channels_last, sample_grid_reference, sample_points
from eventrecon.errors import InputError
from eventrecon.sim.jit import GRAIN, numba_threads


def _lines(rank: int, sizes: tuple[int, ...], dtype: torch.dtype, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    return [channels_last(torch.randn(FEATURES * rank, s, generator=g, dtype=dtype))
            .requires_grad_(True) for s in sizes]


def _coords(n: int, dtype: torch.dtype, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    c = torch.rand(n, 4, generator=g, dtype=dtype) * 2.4 - 1.2       # some outside [-1, 1]
    c[:2] = torch.tensor([[-1.0] * 4, [1.0] * 4], dtype=dtype)        # the edges
    return c


def _by_line(lines, coords, align: bool, padding: str, rank: int) -> torch.Tensor:
    """The rank sum as the field computes it without fusion: each line sampled by
    ``baselines.interp``, then the products and ``Tensor.sum``."""
    s = [sample_points(line, coords[:, a:a + 1], align, padding) for a, line in enumerate(lines)]
    return (s[0] * s[1] * s[2] * s[3]).reshape(-1, FEATURES, rank).sum(-1)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("rank,sizes", [(1, (4, 3, 5, 2)), (3, (7, 5, 9, 4)),
                                        (16, (40, 23, 16, 24))])
@pytest.mark.parametrize("align,padding", [(False, "zeros"), (True, "zeros"),
                                           (False, "border")])
def test_gradients_equal_line_by_line_and_values_agree(dtype, rank, sizes, align, padding):
    lines = _lines(rank, sizes, dtype)
    coords = _coords(700, dtype)
    w = torch.randn(700, FEATURES, generator=torch.Generator().manual_seed(2), dtype=dtype)
    fused = cp_rank_sum(lines, coords, [align] * 4, padding, rank)
    assert fused is not None and fused.shape == (700, FEATURES)
    g_fused = torch.autograd.grad((fused * w).sum(), lines)
    samples = [sample_grid_reference(line, coords[:, a:a + 1], align, padding).t()
               for a, line in enumerate(lines)]
    ref = _by_line(lines, coords, align, padding, rank)
    g_ref = torch.autograd.grad((ref * w).sum(), lines)
    for a, b in zip(g_fused, g_ref):
        assert torch.equal(a, b)                                    # the same sums, in order
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    assert torch.allclose(fused, ref, rtol=tol, atol=tol)
    # an independent reference: the explicit corner gather, in float64
    exact = (samples[0].double() * samples[1].double() * samples[2].double()
             * samples[3].double()).reshape(-1, FEATURES, rank).sum(-1)
    assert (fused.double() - exact).abs().max().item() <= 10 * tol * max(1.0, exact.abs().max())
    with torch.no_grad():                                           # no graph: the same
        assert torch.equal(cp_rank_sum(lines, coords, [align] * 4, padding, rank), fused.detach())


def test_a_non_finite_coordinate_reads_nan_as_line_by_line():
    lines = _lines(2, (5, 6, 7, 4), torch.float32)
    coords = _coords(50, torch.float32)
    coords[7, 2], coords[9, 0] = float("nan"), float("inf")
    fused = cp_rank_sum(lines, coords, [False] * 4, "zeros", 2)
    assert fused[7].isnan().all() and torch.isfinite(fused[:7]).all()
    ref = _by_line(lines, coords, False, "zeros", 2)
    assert torch.equal(fused.isnan(), ref.isnan())
    g = torch.autograd.grad(fused[:7].sum(), lines)          # NaN · 0 reaches both alike
    g_ref = torch.autograd.grad(ref[:7].sum(), lines)
    for a, b in zip(g, g_ref):
        assert torch.equal(a.isnan(), b.isnan()) and torch.equal(a.nan_to_num(), b.nan_to_num())


def test_a_vertex_outside_a_line_is_not_read():
    """Row 0 of a line made non-finite (a diverged parameter): a point whose vertices are
    row 4 and one outside stays finite, as line by line; one that reads row 0 does not;
    no point gives an empty result."""
    lines = _lines(2, (5, 6, 7, 4), torch.float32)
    coords = torch.tensor([[0.9, 0.0, 0.0, 0.0], [-0.95, 0.0, 0.0, 0.0]])   # x: 4.25, -0.375
    with torch.no_grad():
        lines[0][:, 0] = float("inf")
    fused = cp_rank_sum(lines, coords, [False] * 4, "zeros", 2)
    ref = _by_line(lines, coords, False, "zeros", 2)
    assert torch.isfinite(fused[0]).all() and torch.equal(fused[0], ref[0])
    assert not torch.isfinite(fused[1]).all() and not torch.isfinite(ref[1]).all()
    empty = cp_rank_sum(lines, coords[:0], [False] * 4, "zeros", 2)
    assert empty.shape == (0, FEATURES)
    assert all(g.abs().sum() == 0 for g in torch.autograd.grad(empty.sum(), lines))


def test_the_cases_left_to_the_line_by_line_path():
    lines = _lines(2, (5, 6, 7, 4), torch.float32)
    coords = _coords(10, torch.float32)
    assert supported(lines, coords, [False] * 4)
    assert cp_rank_sum(lines, coords.double(), [False] * 4, "zeros", 2) is None      # dtypes
    assert cp_rank_sum(lines, coords.requires_grad_(True), [False] * 4, "zeros", 2) is None
    assert cp_rank_sum(lines[:3], coords.detach(), [False] * 3, "zeros", 2) is None   # 3 lines
    assert cp_rank_sum(lines, coords.detach(), [False, True, False, False], "zeros", 2) is None
    assert not supported([line.to("meta") for line in lines], coords.detach(), [False] * 4)
    assert cp_rank_sum(lines, coords.detach()[:, :3], [False] * 4, "zeros", 2) is None  # [N, 3]
    other = _lines(3, (5, 6, 7, 4), torch.float32)            # 12 channels against 8
    assert cp_rank_sum([*lines[:3], other[3]], coords.detach(), [False] * 4, "zeros", 2) is None
    with pytest.raises(InputError, match="rank: expected a divisor of the lines' 8 channels"):
        cp_rank_sum(lines, coords.detach(), [False] * 4, "zeros", 3)


def test_the_tensorf_cp_field_fused_equals_the_field_line_by_line(monkeypatch):
    field = TensoRFCPField(rank=4, resolution_init=(9, 8, 7, 6), resolution_final=(9, 8, 7, 6),
                           n_stages=1)
    out = fused_and_by_factor(field, tensorf_cp, "cp_rank_sum", monkeypatch)
    (s1, c1, g1), (s2, c2, g2) = out
    assert torch.allclose(s1, s2, rtol=1e-5) and torch.allclose(c1, c2, rtol=1e-5, atol=1e-7)
    for a, b in zip(g1, g2):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-7)


@pytest.mark.skipif(numba_threads() < 2, reason="numba has one thread here")
def test_split_between_two_threads_same_values_and_the_halves_gradients_summed(monkeypatch):
    """With two torch threads the points run as two ranges on numba's threads: the same
    values to the bit, and the lines' gradients exactly the sum of each half's
    one-thread gradient (the ranges scatter into their own copies, added once)."""
    import baselines.cp_fused as cp_fused

    n = 4 * GRAIN
    lines = _lines(16, (40, 23, 16, 24), torch.float32)
    counts = split_between_two_threads(
        cp_fused, lambda c: cp_rank_sum(lines, c, [False] * 4, "zeros", 16), lines,
        _coords(n, torch.float32), monkeypatch)
    # the no-grad forward ran once more on two threads
    assert counts == {"_forward_parts": 2, "_backward_parts": 1}
