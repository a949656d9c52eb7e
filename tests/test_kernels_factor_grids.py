"""The factorised backbones' compiled rank sums (:mod:`eventrecon.kernels.factor_grids`)
against their PyTorch reference, a field built with ``implementation="numba"`` against
the same field with ``"torch"`` (``FactorisedField.rank_sum`` over ``grid_sample``):
TensoRF-CP's four line products and HexPlane's three plane · plane · line products, the
values and the factors' gradients to rounding and against an independent fp64 corner
gather; a non-finite coordinate and a corner outside a factor; the halves' gradients
summed on two threads; what each kernel declines; the corners and weights
(``vertex_corners``) against ``grid_sample``'s formulas to the bit; the channel-last
layout of the factors the kernels read."""

from __future__ import annotations

import re
from collections.abc import Callable

import pytest
import torch
from torch import Tensor

import eventrecon.kernels.factor_grids as factor_grids
from baselines import HexPlaneField, TensoRFCPField
from baselines.factorised import FEATURES, FactorisedField
from baselines.grids import channels_last, sample_grid_reference, vertex_coords
from eventrecon.common.errors import InputError
from eventrecon.kernels.factor_grids import (
    cp_rank_sum,
    cp_unsupported,
    hex_rank_sum,
    hex_unsupported,
    vertex_corners,
)
from eventrecon.kernels.jit import GRAIN, numba_threads, parts
from eventrecon.sim.pipeline import torch_threads


@pytest.fixture(autouse=True)
def _one_thread():
    """One torch thread (the kernels then run their serial loops); the two-thread tests
    ask for two inside."""
    with torch_threads(1):
        yield


def _randomise(field: FactorisedField, seed: int) -> FactorisedField:
    """Factors of O(1) (the initial ``N(0, 1/R²)`` products are tiny)."""
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in field.grids.factors:
            p.copy_(torch.randn(p.shape, generator=g, dtype=p.dtype))
    return field


def _cp(rank: int, sizes: tuple[int, ...], implementation: str, dtype=torch.float32,
        align: bool = False, padding: str = "zeros", seed: int = 0) -> TensoRFCPField:
    """A TensoRF-CP field at ``sizes`` (no growth) with random O(1) lines, read with
    ``align``/``padding``."""
    f = TensoRFCPField(rank=rank, resolution_init=sizes, resolution_final=sizes, n_stages=1,
                       implementation=implementation).to(dtype)
    f.grids.align_corners = [align] * 4
    f.grids.padding = padding
    return _randomise(f, seed + 7)


def _hex(implementation: str, resolution=(9, 9, 9, 5), layout: str = "authors", rank: int = 3,
         dtype=torch.float32, padding: str = "zeros", seed: int = 0) -> HexPlaneField:
    """A HexPlane field with random O(1) factors."""
    f = HexPlaneField(rank=rank, resolution=resolution, spacetime_layout=layout,
                      implementation=implementation).to(dtype)
    f.grids.padding = padding
    return _randomise(f, seed + 7)


def _coords(n: int, dtype: torch.dtype, seed: int = 1) -> Tensor:
    g = torch.Generator().manual_seed(seed)
    c = torch.rand(n, 4, generator=g, dtype=dtype) * 2.4 - 1.2       # some outside [-1, 1]
    c[:2] = torch.tensor([[-1.0] * 4, [1.0] * 4], dtype=dtype)        # the edges
    return c


def _sum_and_grads(field: FactorisedField, coords: Tensor, w: Tensor,
                   features: int = FEATURES) -> tuple[Tensor, tuple[Tensor, ...]]:
    """``field.rank_sum(coords)`` and the factors' gradients of ``Σ out · w``."""
    out = field.rank_sum(coords, features)
    return out, torch.autograd.grad((out * w).sum(), list(field.grids.factors))


def _close(a: Tensor, b: Tensor, tol: float) -> bool:
    """``max |a − b| <= tol · max(1, max |b|)``: equal to rounding."""
    return (a - b).abs().max().item() <= tol * max(1.0, b.abs().max().item())


def _agree(kernel: FactorisedField, ref: FactorisedField, coords: Tensor) -> Tensor:
    """Assert the kernel's rank sum and factor gradients (under random output weights)
    equal the reference field's to :func:`_tol`; the kernel's rank sum ``[N, F]``."""
    dtype = coords.dtype
    w = torch.randn(coords.shape[0], FEATURES, generator=torch.Generator().manual_seed(2),
                    dtype=dtype)
    out, g = _sum_and_grads(kernel, coords, w)
    out_ref, g_ref = _sum_and_grads(ref, coords, w)
    assert out.shape == (coords.shape[0], FEATURES) and out.dtype == dtype
    tol = _tol(dtype)
    assert _close(out, out_ref, tol)
    for a, b in zip(g, g_ref):
        assert _close(a, b, tol)
    return out


def _tol(dtype: torch.dtype) -> float:
    return 1e-5 if dtype == torch.float32 else 1e-12


# ---------------------------------------------------------------- TensoRF-CP
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("rank,sizes", [(1, (4, 3, 5, 2)), (3, (7, 5, 9, 4)),
                                        (16, (40, 23, 16, 24))])
@pytest.mark.parametrize("align,padding", [(False, "zeros"), (True, "zeros"),
                                           (False, "border")])
def test_cp_values_and_gradients_agree_with_the_reference(dtype, rank, sizes, align, padding):
    """The kernel's rank sum and line gradients equal the reference's to rounding, and
    its values an independent fp64 corner gather; with no graph the same bits."""
    kernel = _cp(rank, sizes, "numba", dtype, align, padding)
    ref = _cp(rank, sizes, "torch", dtype, align, padding)
    coords = _coords(700, dtype)
    out = _agree(kernel, ref, coords)
    tol = _tol(dtype)
    # an independent reference: the explicit corner gather, in float64
    s = [sample_grid_reference(line.double(), coords[:, a:a + 1].double(), align, padding).t()
         for a, line in enumerate(kernel.grids.factors)]
    exact = (s[0] * s[1] * s[2] * s[3]).reshape(-1, FEATURES, rank).sum(-1)
    assert _close(out.double(), exact, 10 * tol)
    with torch.no_grad():                                           # no graph: the same
        assert torch.equal(kernel.rank_sum(coords), out.detach())


def test_cp_a_non_finite_coordinate_reads_nan_as_the_reference():
    kernel, ref = _cp(2, (5, 6, 7, 4), "numba"), _cp(2, (5, 6, 7, 4), "torch")
    coords = _coords(50, torch.float32)
    coords[7, 2], coords[9, 0] = float("nan"), float("inf")
    out, ref_out = kernel.rank_sum(coords), ref.rank_sum(coords)
    assert out[7].isnan().all() and out[9].isnan().all() and torch.isfinite(out[:7]).all()
    assert torch.equal(out.isnan(), ref_out.isnan())
    g = torch.autograd.grad(out[:7].sum(), list(kernel.grids.factors))
    g_ref = torch.autograd.grad(ref_out[:7].sum(), list(ref.grids.factors))
    for a, b in zip(g, g_ref):                      # NaN · 0 reaches both alike
        assert torch.equal(a.isnan(), b.isnan()) and a.isnan().any()
        assert _close(a.nan_to_num(), b.nan_to_num(), 1e-5)


def test_cp_a_vertex_outside_a_line_is_not_read():
    """Row 0 of a line made non-finite (a diverged parameter): a point whose vertices are
    row 4 and one outside stays finite, as with the reference; one that reads row 0 does
    not; no point gives an empty result."""
    fields = [_cp(2, (5, 6, 7, 4), impl) for impl in ("numba", "torch")]
    coords = torch.tensor([[0.9, 0.0, 0.0, 0.0], [-0.95, 0.0, 0.0, 0.0]])   # x: 4.25, -0.375
    for f in fields:
        with torch.no_grad():
            f.grids.factors[0][:, 0] = float("inf")
    out, ref = (f.rank_sum(coords) for f in fields)
    assert torch.isfinite(out[0]).all() and _close(out[0], ref[0], 1e-6)
    assert not torch.isfinite(out[1]).all() and not torch.isfinite(ref[1]).all()
    empty = fields[0].rank_sum(coords[:0])
    assert empty.shape == (0, FEATURES)
    assert all(g.abs().sum() == 0
               for g in torch.autograd.grad(empty.sum(), list(fields[0].grids.factors)))


def test_cp_the_cases_the_kernel_declines():
    """``cp_unsupported`` names what a call lacks; ``cp_rank_sum`` raises it."""
    lines = list(_cp(2, (5, 6, 7, 4), "numba").grids.factors)
    coords = _coords(10, torch.float32)
    align = [False] * 4
    assert cp_unsupported(lines, coords, align) is None
    cases = [
        ((lines, coords.double(), align), "factors and coordinates of one dtype"),
        ((lines, coords.clone().requires_grad_(True), align),
         "no gradient with respect to the coordinates"),
        ((lines[:3], coords, align[:3]), "four lines [C, R]"),
        ((lines, coords, [False, True, False, False]), "lines of one sampling convention"),
        (([line.to("meta") for line in lines], coords, align), "tensors on the CPU"),
        ((lines, coords[:, :3], align), "coordinates [N, 4]"),
        (([*lines[:3], _cp(3, (5, 6, 7, 4), "numba").grids.factors[3]], coords, align),
         "factors of one channel count"),                      # 12 channels against 8
    ]
    for (ls, c, ac), reason in cases:
        assert cp_unsupported(ls, c, ac) is not None
        assert cp_unsupported(ls, c, ac).startswith(reason), reason
        if not any(line.device.type == "meta" for line in ls):
            with pytest.raises(InputError, match=re.escape(f"factors: expected {reason}")):
                cp_rank_sum(ls, c, ac, "zeros", 2)
    with torch.no_grad():                      # no gradient wanted: the kernel applies
        assert cp_unsupported(lines, coords.clone().requires_grad_(True), align) is None
    with pytest.raises(InputError, match="rank: expected a divisor of the factors' 8 channels"):
        cp_rank_sum(lines, coords, align, "zeros", 3)


def test_cp_field_with_the_kernel_equals_the_field_with_the_reference():
    """σ, rgb and the lines' gradients of the whole field (box normalisation,
    activations), the kernel against the reference."""
    results = [_field_step(TensoRFCPField(rank=4, resolution_init=(9, 8, 7, 6),
                                          resolution_final=(9, 8, 7, 6), n_stages=1,
                                          implementation=impl))
               for impl in ("numba", "torch")]
    _assert_steps_agree(*results)


# ---------------------------------------------------------------- HexPlane
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("layout", ["authors", "swapped"])
@pytest.mark.parametrize("padding", ["zeros", "border"])
def test_hex_values_and_gradients_agree_with_the_reference(dtype, layout, padding):
    kernel = _hex("numba", layout=layout, dtype=dtype, padding=padding)
    ref = _hex("torch", layout=layout, dtype=dtype, padding=padding)
    coords = _coords(900, dtype)
    out = _agree(kernel, ref, coords)
    tol = _tol(dtype)
    # an independent reference: the explicit corner gathers, in float64
    grids = kernel.grids
    s = [sample_grid_reference(p.double(), coords[:, list(ax)].double(), ac, padding).t()
         for p, ax, ac in zip(grids.factors, grids.axes, grids.align_corners)]
    exact = sum(s[k] * s[k + 3] * s[k + 6] for k in range(3))
    exact = exact.reshape(-1, FEATURES, kernel.rank).sum(-1)
    assert _close(out.double(), exact, 10 * tol)
    with torch.no_grad():                                       # no graph: the same
        assert torch.equal(kernel.rank_sum(coords), out.detach())


def test_hex_density_alone_reads_the_leading_channels_and_its_gradient_reaches_them_only():
    kernel, ref = _hex("numba", rank=4), _hex("torch", rank=4)
    coords = _coords(300, torch.float32)
    w = torch.ones(300, 1)
    out, g = _sum_and_grads(kernel, coords, w, features=1)
    out_ref, g_ref = _sum_and_grads(ref, coords, w, features=1)
    assert out.shape == (300, 1) and _close(out, out_ref, 1e-5)
    for a, b in zip(g, g_ref):
        assert _close(a, b, 1e-5) and a[4:].abs().sum() == 0 and a[:4].abs().sum() > 0


def test_hex_a_non_finite_coordinate_reads_nan_and_a_corner_outside_is_not_read():
    """A point below the grid's lower edge has its lower corner at vertex −1, outside: it
    must read vertex 0 only, not wrap round to the last row (made non-finite here, a
    diverged parameter); NaN and inf coordinates read NaN; the gradients, NaN included,
    are the reference's."""
    fields = [_hex(impl) for impl in ("numba", "torch")]
    coords = _coords(60, torch.float32)
    coords[7, 2], coords[9, 3] = float("nan"), float("inf")
    for f in fields:
        with torch.no_grad():                   # P_xy reads y along its first grid axis
            f.grids.factors[0][:, -1, :] = float("inf")
    coords[11] = torch.tensor([0.0, -1.05, 0.0, 0.0])           # y below the lower edge
    coords[12] = torch.tensor([0.0, 1.0, 0.0, 0.0])             # on the last row
    runs = []
    for f in fields:
        o = f.rank_sum(coords)
        runs.append((o, torch.autograd.grad(o[:11].sum(), list(f.grids.factors))))
    (out, g), (ref, g_ref) = runs
    assert out[7].isnan().all() and out[9].isnan().all()
    assert torch.equal(out.isnan(), ref.isnan())
    assert torch.isfinite(out[11]).all() and not torch.isfinite(out[12]).all()
    for a, b in zip(g, g_ref):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5, equal_nan=True)
    empty = fields[0].rank_sum(coords[:0])
    assert empty.shape == (0, FEATURES)
    assert all(g.abs().sum() == 0
               for g in torch.autograd.grad(empty.sum(), list(fields[0].grids.factors)))


def test_hex_the_cases_the_kernel_declines(monkeypatch):
    f = _hex("numba")
    g, coords = f.grids, _coords(10, torch.float32)
    factors = g.leading(None)
    assert hex_unsupported(factors, g.axes, coords, g.align_corners) is None
    structure = "six planes then three lines"
    cases = [
        ((factors, g.axes, coords.double(), g.align_corners),
         "factors and coordinates of one dtype"),
        ((factors, g.axes, coords.clone().requires_grad_(True), g.align_corners),
         "no gradient with respect to the coordinates"),
        ((factors[:8], g.axes[:8], coords, g.align_corners[:8]), structure),   # 8 factors
        ((factors, g.axes, coords, [True] * 5 + [False] * 4),               # two conventions
         "planes of one sampling convention and lines of one"),
        (([p.to("meta") for p in factors], g.axes, coords, g.align_corners),
         "tensors on the CPU"),
        ((factors, g.axes, coords[:, :3], g.align_corners), "coordinates [N, 4]"),
        ((factors, [*g.axes[:8], (0, 1)], coords, g.align_corners), structure),  # a line of 2
        ((factors, [*g.axes[:8], (4,)], coords, g.align_corners), structure),    # no column 4
    ]
    for args, reason in cases:
        assert (hex_unsupported(*args) or "").startswith(reason), reason
        if args[0][0].device.type != "meta":
            with pytest.raises(InputError, match=re.escape(f"factors: expected {reason}")):
                hex_rank_sum(*args[:3], args[3], "zeros", 3)
    paper = ([torch.empty(32, 500, 500, device="meta")] * 3
             + [torch.empty(32, 500, 24, device="meta")] * 3
             + [torch.empty(32, 500, device="meta")] * 3)          # the authors' size
    assert hex_unsupported(paper, g.axes, coords, g.align_corners).startswith(
        "factors of at most 6291456 bytes")
    with monkeypatch.context() as m:                             # too large to stay in cache
        m.setattr(factor_grids, "MAX_BYTES", sum(p.numel() * 4 for p in factors) - 4)
        assert hex_unsupported(factors, g.axes, coords, g.align_corners).startswith(
            "factors of at most")
    assert hex_unsupported(factors, g.axes, coords, g.align_corners) is None
    with pytest.raises(InputError, match="rank: expected a divisor of the factors' 12 channels"):
        hex_rank_sum(factors, g.axes, coords, g.align_corners, "zeros", 5)


def test_hex_field_with_the_kernel_equals_the_field_with_the_reference():
    results = [_field_step(_hex(impl, resolution=(10, 10, 10, 6), rank=4), n=400)
               for impl in ("numba", "torch")]
    _assert_steps_agree(*results)


# ---------------------------------------------------------------- both kernels
def _field_step(field: FactorisedField, n: int = 300) -> tuple[Tensor, Tensor, list[Tensor]]:
    """``(σ, rgb, factor gradients of Σσ + Σrgb)`` of ``field`` at ``n`` random points."""
    g = torch.Generator().manual_seed(3)
    xyz, t = torch.rand(n, 3, generator=g) * 2 - 1, torch.rand(n, 1, generator=g)
    field.zero_grad(set_to_none=True)
    sigma, rgb = field(xyz, t)
    (sigma.sum() + rgb.sum()).backward()
    return sigma.detach(), rgb.detach(), [p.grad.clone() for p in field.grids.factors]


def _assert_steps_agree(a: tuple, b: tuple) -> None:
    (s1, c1, g1), (s2, c2, g2) = a, b
    assert torch.allclose(s1, s2, rtol=1e-5) and torch.allclose(c1, c2, rtol=1e-5, atol=1e-7)
    for x, y in zip(g1, g2):
        assert _close(x, y, 1e-5)


@pytest.mark.parametrize("kind", ["tensorf_cp", "hexplane"])
def test_second_order_gradients_through_a_kernel_are_refused(kind):
    """The kernels' backward is not itself differentiable: asking for a gradient of the
    gradient raises instead of returning one that silently ignores it."""
    f = _cp(2, (5, 6, 7, 4), "numba") if kind == "tensorf_cp" else _hex("numba")
    out = f.rank_sum(_coords(40, torch.float32))
    g = torch.autograd.grad(out.square().sum(), list(f.grids.factors), create_graph=True)
    with pytest.raises(RuntimeError):
        sum(x.sum() for x in g).backward()


def _split_between_two_threads(rank_sum: Callable[[Tensor], Tensor], params: list[Tensor],
                               coords: Tensor, names: tuple[str, str],
                               monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Check a compiled rank sum ``rank_sum(coords) -> [N, F]`` split between two torch
    threads: the same values as on one, to the bit, and the gradients of ``params``
    exactly the sum of each half's one-thread gradient (the ranges scatter into their own
    copies, added once). Returns how often the parallel forward and backward loops
    ``names`` of :mod:`~eventrecon.kernels.factor_grids` ran on the two threads."""
    n = coords.shape[0]
    w = torch.randn(n, FEATURES, generator=torch.Generator().manual_seed(2), dtype=coords.dtype)

    def run(rows: slice) -> tuple[Tensor, tuple[Tensor, ...]]:
        out = rank_sum(coords[rows])
        return out.detach(), torch.autograd.grad((out * w[rows]).sum(), params)

    one, _ = run(slice(None))
    halves = [run(slice(0, n // 2))[1], run(slice(n // 2, n))[1]]
    calls: list[list[int]] = [[], []]
    with monkeypatch.context() as m:
        for name, c in zip(names, calls):
            kernel = getattr(factor_grids, name)
            m.setattr(factor_grids, name, lambda *a, c=c, k=kernel: (c.append(1), k(*a))[1])
        with torch_threads(2):
            assert parts(n, GRAIN) == 2
            two, g_two = run(slice(None))
            with torch.no_grad():
                assert torch.equal(rank_sum(coords), one)
    assert torch.equal(two, one)
    for a, b0, b1 in zip(g_two, *halves):
        assert torch.equal(a, b0 + b1)
    return [len(c) for c in calls]


@pytest.mark.skipif(numba_threads() < 2, reason="numba has one thread here")
def test_cp_split_between_two_threads_same_values_and_the_halves_gradients_summed(monkeypatch):
    """With two torch threads the points run as two ranges on numba's threads: the same
    values to the bit, and the lines' gradients exactly the sum of each half's
    one-thread gradient."""
    f = _cp(16, (40, 23, 16, 24), "numba")
    counts = _split_between_two_threads(f.rank_sum, list(f.grids.factors),
                                        _coords(4 * GRAIN, torch.float32),
                                        ("_cp_forward_parts", "_cp_backward_parts"), monkeypatch)
    assert counts == [2, 1]          # the no-grad forward ran once more on two threads


@pytest.mark.skipif(numba_threads() < 2, reason="numba has one thread here")
def test_hex_split_between_two_threads_same_values_and_the_halves_gradients_summed(monkeypatch):
    f = _hex("numba", resolution=(16, 16, 16, 8), rank=4)
    counts = _split_between_two_threads(f.rank_sum, list(f.grids.factors),
                                        _coords(4 * GRAIN, torch.float32),
                                        ("_hex_forward_parts", "_hex_backward_parts"),
                                        monkeypatch)
    assert counts == [2, 1]


# ---------------------------------------------------------------- corners and weights
def _bits(x: Tensor) -> Tensor:
    """The values' bit patterns (signed zeros and NaN payloads told apart)."""
    return x.contiguous().view(torch.int32 if x.dtype == torch.float32 else torch.int64)


def _corners_reference(p: Tensor) -> tuple[Tensor, Tensor]:
    """Vertex units ``p [N, d]`` → the lower vertex ``⌊p⌋`` (−2 for a non-finite or very
    negative one, 2³¹ for a huge one) and the weights ``(1 − (p − ⌊p⌋), p − ⌊p⌋)``, in
    tensor operations."""
    lo = p.floor()
    frac = p - lo
    lower = torch.where(~torch.isfinite(lo) | (lo < -2), torch.full_like(lo, -2.0), lo)
    lower = torch.where(lower > 2.0 ** 31, torch.full_like(lo, 2.0 ** 31), lower)
    return lower.long(), torch.stack([1 - frac, frac], dim=-1)


def test_vertex_corners_known_values():
    """On a line of 5 vertices with ``align_corners``: 0.375 is vertex unit 2.75 (lower
    vertex 2, weights 0.25, 0.75), −0.5 is vertex 1 exactly; NaN and ±inf have no vertex
    inside (−2) and NaN weights; a huge value lies beyond every factor (2³¹)."""
    c = torch.tensor([[float("nan"), 0.375], [-0.5, float("inf")], [1e30, -1e30],
                      [-float("inf"), 1.0]])
    lower, w = vertex_corners(c, (5, 5), True, "zeros")
    assert lower.tolist() == [[-2, 2], [1, -2], [2 ** 31, -2], [-2, 4]]
    assert w[0, 1].tolist() == [0.25, 0.75] and w[1, 0].tolist() == [1.0, 0.0]
    assert w[0, 0].isnan().all() and w[1, 1].isnan().all() and w[3, 0].isnan().all()
    assert w[3, 1].tolist() == [1.0, 0.0]
    border = vertex_corners(c, (5, 5), True, "border")              # clamped to [0, 4]
    assert border[0].tolist() == [[-2, 2], [1, 4], [4, 0], [0, 4]]
    plain = vertex_corners(torch.tensor([[-1.0], [1.0]]), (5,), False, "zeros")  # −0.5, 4.5
    assert plain[0].flatten().tolist() == [-1, 4] and plain[1][:, 0].tolist() == [[0.5, 0.5]] * 2


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("align,padding", [(True, "zeros"), (False, "zeros"), (True, "border"),
                                           (False, "border")])
def test_vertex_corners_equal_the_tensor_form_to_the_bit(dtype, align, padding):
    """The compiled pass from normalised coordinates to corners and weights against
    ``grid_sample``'s vertex units (``baselines.grids.vertex_coords``) floored in tensor
    operations, on random points inside and outside the grid and on the edges, NaN,
    ±inf, huge values and −0: the same lower corners and the same bits."""
    g = torch.Generator().manual_seed(5)
    c = torch.rand(20_000, 3, generator=g, dtype=dtype) * 2.6 - 1.3
    c[:4] = torch.tensor([[-1.0, 1.0, 0.0], [1.0, -1.0, -0.0], [0.5, 0.25, -0.5],
                          [-1.0, -1.0, -1.0]], dtype=dtype)
    c[4, 0], c[5, 1], c[6, 2], c[7, 0], c[8, 1] = (float("nan"), float("inf"), -float("inf"),
                                                    1e30, -1e30)
    for sizes in ((128, 24, 7), (2, 3, 500)):
        for points, axes in ((c, None), (c[:, [2, 0]], None), (c, [2, 0])):   # columns too
            d = points.shape[1] if axes is None else len(axes)
            low, w = vertex_corners(points, sizes[:d], align, padding, axes)
            picked = points if axes is None else points[:, axes]
            ref_low, ref_w = _corners_reference(vertex_coords(picked, sizes[:d], align,
                                                              padding))
            assert low.dtype == torch.long and w.dtype == dtype and low.shape == (20_000, d)
            assert torch.equal(low, ref_low) and torch.equal(_bits(w), _bits(ref_w))


def test_vertex_corners_refuse_axes_that_do_not_fit():
    c = torch.zeros(5, 4)
    for sizes, axes in (((9,), (3, 0)), ((9, 7), (3, 4)), ((9, 7, 5), None)):
        with pytest.raises(InputError, match="axes/sizes"):
            vertex_corners(c, sizes, False, "zeros", axes)


@pytest.mark.skipif(numba_threads() < 2, reason="numba has one thread here")
def test_vertex_corners_split_between_two_threads_gives_the_same_bits(monkeypatch):
    calls = []
    kernel = factor_grids._vertex_corners_parts
    monkeypatch.setattr(factor_grids, "_vertex_corners_parts",
                        lambda *a: (calls.append(1), kernel(*a))[1])
    c = torch.rand(4 * GRAIN, 4, generator=torch.Generator().manual_seed(8)) * 2.4 - 1.2
    one = vertex_corners(c, (9, 7), False, "zeros", (3, 0))
    with torch_threads(2):
        two = vertex_corners(c, (9, 7), False, "zeros", (3, 0))
    assert calls == [1]
    assert torch.equal(one[0], two[0]) and torch.equal(_bits(one[1]), _bits(two[1]))


# ---------------------------------------------------------------- the factors' layout
@pytest.mark.parametrize("kind", ["tensorf_cp", "hexplane"])
def test_factor_grids_are_channel_last_and_their_gradients_stay_so(kind):
    """On a CPU the factors keep their ``[C, *R]`` shape and values but store channels
    innermost (the rows the kernels read without a copy), at initialisation, after
    growth, after loading a contiguous (older) state dict and after a cast; off the CPU
    they are contiguous; the kernel's gradient arrives in the same layout (no copy by
    autograd). The field equals the reference field to rounding, gradients too."""
    cls = TensoRFCPField if kind == "tensorf_cp" else HexPlaneField
    kw = ({"rank": 3, "resolution_init": (6, 6, 6, 5), "resolution_final": (9, 9, 9, 7),
           "n_stages": 2, "growth_steps": 10} if kind == "tensorf_cp"
          else {"rank": 3, "resolution": (9, 9, 9, 7)})
    field = cls(**kw, implementation="numba")

    def channel_last(p):
        return p.movedim(0, -1).is_contiguous()

    assert all(channel_last(p) for p in field.grids.factors)
    g = torch.Generator().manual_seed(2)
    xyz, t = torch.rand(700, 3, generator=g) * 2 - 1, torch.rand(700, 1, generator=g)
    w = torch.randn(700, 4, generator=g)
    results = []
    for f in (field, cls(**kw, implementation="torch")):
        sigma, rgb = f(xyz, t)
        (torch.cat([sigma[:, None], rgb], 1) * w).sum().backward()
        if f is field:
            assert all(channel_last(p.grad) for p in f.grids.factors)
        results.append((sigma.detach(), rgb.detach(), [p.grad.clone() for p in f.grids.factors]))
    (s1, c1, g1), (s2, c2, g2) = results
    assert torch.allclose(s1, s2, rtol=1e-5, atol=1e-6)
    assert torch.allclose(c1, c2, rtol=1e-5, atol=1e-6)
    for a, b in zip(g1, g2):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-6)
    if kind == "tensorf_cp":
        field.upsample((9, 9, 9, 7))
        assert all(channel_last(p) for p in field.grids.factors)
    state = {k: v.contiguous() for k, v in field.state_dict().items()}
    fresh = cls(**kw)
    fresh.load_state_dict(state)
    assert all(channel_last(p) for p in fresh.grids.factors)
    for a, b in zip(fresh.grids.factors, field.grids.factors):
        assert torch.equal(a, b)
    for p in fresh.grids.factors:                        # gradients follow their factors
        p.grad = torch.ones_like(p)
    fresh.double()                                       # a cast keeps the CPU layout
    assert all(channel_last(p) and p.dtype == torch.float64 and channel_last(p.grad)
               for p in fresh.grids.factors)
    fresh.to("meta")                                     # off the CPU: contiguous, as before
    assert all(p.is_contiguous() and p.grad.is_contiguous() for p in fresh.grids.factors)


def test_channels_last_keeps_shape_and_values():
    grid = torch.randn(4, 5, 6, generator=torch.Generator().manual_seed(1))
    last = channels_last(grid)
    assert last.shape == grid.shape and torch.equal(last, grid) and last.stride() == (1, 24, 4)
    assert torch.equal(factor_grids.channel_rows(last), grid.reshape(4, -1).t())


def test_moments_loaded_in_another_layout_take_their_parameters_layout():
    """A checkpoint written before the factors were stored channel-last (or on another
    device) holds contiguous AdamW moments. Fused AdamW on a CPU walks a parameter and its
    moments as flat memory, so without the module's load hook (``state_like_params``) it
    pairs moments with the wrong elements (checked here: a visibly wrong step). With the
    hook the moments take the parameters' strides, and the step equals the unfused one on
    contiguous tensors."""
    import copy

    from eventrecon.engine.module import state_like_params

    g = torch.Generator().manual_seed(4)
    field = HexPlaneField(rank=2, resolution=(6, 6, 6, 5))
    params = [p.detach() for p in field.grids.factors]
    grads = [torch.randn(p.shape, generator=g) for p in params]
    older = [torch.nn.Parameter(p.contiguous()) for p in params]       # the old layout
    opt_old = torch.optim.AdamW(older, lr=0.1, fused=True)
    for q, gr in zip(older, grads):
        q.grad = gr.clone()
    opt_old.step()
    saved = opt_old.state_dict()

    def step(layout: bool, hook: bool) -> list[Tensor]:
        ps = [torch.nn.Parameter(p.clone(memory_format=torch.preserve_format) if layout
                                 else p.contiguous()) for p in params]
        opt = torch.optim.AdamW(ps, lr=0.1, fused=layout)
        if hook:
            opt.register_load_state_dict_post_hook(state_like_params)
        opt.load_state_dict(copy.deepcopy(saved))         # fused: as saved
        for p, gr in zip(ps, grads):
            p.grad = torch.empty_like(p).copy_(gr)        # as autograd lays it: like p
        opt.step()
        return [p.detach().contiguous() for p in ps]

    reference = step(layout=False, hook=False)
    hooked = step(layout=True, hook=True)
    unhooked = step(layout=True, hook=False)
    assert max((a - b).abs().max().item() for a, b in zip(hooked, reference)) <= 1e-6
    assert max((a - b).abs().max().item() for a, b in zip(unhooked, reference)) > 1e-3


def test_a_grown_float64_field_reloads_in_float64():
    """Loading a grown checkpoint resizes the factors in the saved dtype."""
    kw = {"rank": 2, "resolution_init": (4, 4, 4, 4), "resolution_final": (7, 7, 7, 6),
          "n_stages": 2, "growth_steps": 10}
    grown = TensoRFCPField(**kw).double()
    grown.upsample((7, 7, 7, 6))
    fresh = TensoRFCPField(**kw).double()
    fresh.load_state_dict(grown.state_dict())
    for a, b in zip(fresh.grids.factors, grown.grids.factors):
        assert a.dtype == torch.float64 and torch.equal(a, b)
        assert a.movedim(0, -1).is_contiguous()
