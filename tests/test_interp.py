"""The CPU's compiled multilinear interpolation (baselines.interp): values and
gradients against the explicit corner gather, the cases it hands to ``grid_sample``, and
the channel-last layout of the factor grids that read it."""

from __future__ import annotations

import pytest
import torch

import baselines.grids as grids
import baselines.tensorf_cp as tensorf_cp
from baselines import HexPlaneField, TensoRFCPField
from baselines.interp import corners, interpolate, supported
from eventrecon.errors import InputError
from eventrecon.sim.jit import GRAIN, numba_threads, parts
from eventrecon.sim.pipeline import torch_threads


@pytest.fixture(autouse=True)
def _one_thread():
    with torch_threads(1):
        yield


def _case(shape: tuple[int, ...], n: int, seed: int, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    grid = torch.randn(shape, generator=g, dtype=dtype)
    coords = (torch.rand(n, len(shape) - 1, generator=g, dtype=dtype) * 2.4 - 1.2)
    coords[:4] = torch.tensor([-1.0, 1.0, 1.0, -1.0], dtype=dtype)[:, None]   # the edges
    return grid, coords


@pytest.mark.parametrize("shape", [(3, 7), (5, 2), (3, 5, 9), (4, 2, 6), (2, 4, 5, 6)])
@pytest.mark.parametrize("align,padding", [(True, "zeros"), (False, "zeros"),
                                           (True, "border"), (False, "border")])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_values_and_grid_gradient_match_the_explicit_gather(shape, align, padding, dtype):
    """Forward: the corner gather of ``sample_grid_reference`` (a Python loop over the
    corners, independent of the compiled loops). Backward: autograd through that gather,
    for a random weighting of the outputs."""
    grid, coords = _case(shape, 600, 0, dtype)
    grid.requires_grad_(True)
    out = interpolate(grid, coords, align, padding)
    assert out is not None and out.shape == (600, shape[0]) and out.dtype == dtype
    ref = grids.sample_grid_reference(grid, coords, align, padding).t()
    tol = 1e-6 if dtype == torch.float32 else 1e-13
    assert (out - ref).abs().max().item() <= tol
    w = torch.randn(out.shape, generator=torch.Generator().manual_seed(1), dtype=dtype)
    (g_new,) = torch.autograd.grad((out * w).sum(), grid)
    (g_ref,) = torch.autograd.grad((ref * w).sum(), grid)
    assert (g_new - g_ref).abs().max().item() <= 20 * tol


def test_known_values_and_non_finite_or_far_points():
    """A line ``[0, 1, 4]``: halfway between vertices 1 and 2 reads 2.5; with zero padding
    and ``align_corners=False`` the outer edge (half a cell beyond the last vertex) reads
    half of it. As with ``grid_sample``'s zero padding, a NaN or infinite coordinate reads
    NaN and a huge finite one zero; none of them sends a gradient to the grid. With border
    padding ``±inf`` reads the border vertex, and a NaN still reads NaN."""
    line = torch.tensor([[0.0, 1.0, 4.0]], requires_grad=True)
    c = torch.tensor([[0.5], [1.0], [float("nan")], [1e30], [-1e30], [float("inf")],
                      [-float("inf")]])
    out = interpolate(line, c, True, "zeros").flatten()
    ref = grids.unsplit(grids.sample_grid_split(line.detach(), c, 1, True, "zeros"), 7)
    assert torch.equal(out.isnan(), ref.flatten().isnan())
    assert out.nan_to_num().tolist() == [2.5, 4.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    beyond = interpolate(line.detach(), torch.tensor([[1.0]]), False, "zeros")     # p = 2.5
    assert beyond.item() == pytest.approx(2.0)
    (g,) = torch.autograd.grad(out[:2].sum() + out[3:5].sum(), line, retain_graph=True)
    assert g.flatten().tolist() == [0.0, 0.5, 1.5]
    (g_all,) = torch.autograd.grad(out.nan_to_num().sum(), line)
    assert torch.isfinite(g_all).all()
    border = interpolate(line.detach(), c, True, "border").flatten()
    assert border[[3, 4, 5, 6]].tolist() == [4.0, 0.0, 4.0, 0.0] and border[2].isnan()
    lower, w = corners(torch.tensor([[float("nan"), 2.75], [1.0, float("inf")]]))
    assert lower.tolist() == [[-2, 2], [1, -2]] and w[0, 1].tolist() == [0.25, 0.75]
    assert w[0, 0].isnan().all() and w[1, 1].isnan().all()


def test_coordinates_of_the_wrong_width_are_refused():
    """One column per grid axis, or one error naming the expectation (a line read with two
    columns would otherwise index past the grid's sizes in the compiled loop)."""
    line, plane = torch.zeros(1, 3), torch.zeros(1, 3, 4)
    for grid, coords in ((line, torch.zeros(5, 2)), (plane, torch.zeros(5, 1)),
                         (plane, torch.zeros(5))):
        with pytest.raises(InputError, match=r"coords.*\[N, \d\]"):
            interpolate(grid, coords)
        with pytest.raises(InputError):
            grids.sample_points(grid, coords)


def test_second_order_gradients_are_refused():
    """The scatter is not itself differentiable: asking for a gradient of the gradient
    raises instead of returning one that silently ignores it."""
    grid = torch.randn(2, 5, requires_grad=True)
    out = interpolate(grid, torch.rand(7, 1) * 2 - 1)
    (g,) = torch.autograd.grad(out.square().sum(), grid, create_graph=True)
    with pytest.raises(RuntimeError):
        g.sum().backward()


def test_cases_left_to_grid_sample():
    """A grid of four axes, coordinates that need a gradient, a tensor off the CPU and
    mixed dtypes are not served (``None``); ``sample_points`` then gives ``grid_sample``'s
    values, with the coordinates' gradient."""
    grid, coords = _case((2, 5, 6), 50, 3)
    assert supported(grid, coords)
    assert not supported(torch.zeros(2, 3, 4, 5, 2), torch.zeros(7, 4))
    assert not supported(grid.to("meta"), coords.to("meta"))
    assert not supported(grid, coords.double())
    c = coords.clone().requires_grad_(True)
    assert interpolate(grid, c) is None
    out = grids.sample_points(grid, c, True, "zeros")
    ref = grids.sample_grid_reference(grid, coords, True, "zeros").t()
    assert (out - ref).abs().max().item() <= 1e-5
    (gc,) = torch.autograd.grad(out.sum(), c)
    assert gc.abs().sum().item() > 0
    with torch.no_grad():                     # no gradient wanted: served after all
        assert interpolate(grid, c) is not None


@pytest.mark.parametrize("kind", ["tensorf_cp", "hexplane"])
def test_factor_grids_are_channel_last_and_their_gradients_stay_so(kind, monkeypatch):
    """On a CPU the factors keep their ``[C, *R]`` shape and values but store channels
    innermost, at initialisation, after growth, after loading a contiguous (older) state
    dict and after a cast; off the CPU they are contiguous;
    the gradient arrives in the same layout (no copy by autograd). The field equals the
    ``grid_sample`` field (the compiled path switched off) to rounding, gradients too."""
    cls = TensoRFCPField if kind == "tensorf_cp" else HexPlaneField
    kw = ({"rank": 3, "resolution_init": (6, 6, 6, 5), "resolution_final": (9, 9, 9, 7),
           "n_stages": 2, "growth_steps": 10} if kind == "tensorf_cp"
          else {"rank": 3, "resolution": (9, 9, 9, 7)})
    field = cls(**kw)

    def channel_last(p):
        return p.movedim(0, -1).is_contiguous()

    assert all(channel_last(p) for p in field.grids.factors)
    g = torch.Generator().manual_seed(2)
    xyz, t = torch.rand(700, 3, generator=g) * 2 - 1, torch.rand(700, 1, generator=g)
    w = torch.randn(700, 4, generator=g)
    results = []
    for compiled in (True, False):
        if not compiled:
            monkeypatch.setattr(grids, "interpolate", lambda *a, **k: None)
            monkeypatch.setattr(tensorf_cp, "cp_rank_sum", lambda *a, **k: None)
        field.zero_grad(set_to_none=True)
        sigma, rgb = field(xyz, t)
        (torch.cat([sigma[:, None], rgb], 1) * w).sum().backward()
        if compiled:
            assert all(channel_last(p.grad) for p in field.grids.factors)
        grads = [p.grad.clone() for p in field.grids.factors]
        results.append((sigma.detach(), rgb.detach(), grads))
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


def test_moments_loaded_in_another_layout_take_their_parameters_layout():
    """A checkpoint written before the factors were stored channel-last (or on another
    device) holds contiguous AdamW moments. Fused AdamW on a CPU walks a parameter and its
    moments as flat memory, so without the module's load hook (``state_like_params``) it
    pairs moments with the wrong elements (checked here: a visibly wrong step). With the
    hook the moments take the parameters' strides, and the step equals the unfused one on
    contiguous tensors."""
    import copy

    from eventrecon.module import state_like_params

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

    def step(layout: bool, hook: bool) -> list[torch.Tensor]:
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


@pytest.mark.skipif(numba_threads() < 2, reason="numba has one thread here")
@pytest.mark.parametrize("shape", [(8, 64, 64), (6, 500)])
def test_split_between_two_threads_same_values_and_the_halves_gradients_summed(shape,
                                                                               monkeypatch):
    """With two torch threads the points run as two ranges on numba's threads: the same
    values to the bit, and the grid's gradient exactly the sum of each half's one-thread
    gradient (each range scatters into its own copy, added once). Outside the
    ``torch_threads(2)`` block this module's fixture keeps one thread."""
    import baselines.interp as interp

    split = {k: [] for k in ("_gather_parts", "_scatter_parts")}
    for name, calls in split.items():
        kernel = getattr(interp, name)
        monkeypatch.setattr(interp, name, lambda *a, c=calls, f=kernel: (c.append(1), f(*a))[1])
    n = 4 * GRAIN
    grid, coords = _case(shape, n, 3)
    grid.requires_grad_(True)
    w = torch.randn(n, shape[0], generator=torch.Generator().manual_seed(4))

    def run(rows: slice) -> tuple[torch.Tensor, torch.Tensor]:
        out = interpolate(grid, coords[rows], False, "zeros")
        return out.detach(), torch.autograd.grad((out * w[rows]).sum(), grid)[0]

    one, _ = run(slice(None))
    halves = run(slice(0, n // 2))[1] + run(slice(n // 2, n))[1]
    with torch_threads(2):
        assert parts(n, GRAIN) == 2
        two, g_two = run(slice(None))
        with torch.no_grad():
            assert torch.equal(interpolate(grid, coords, False, "zeros"), one)
    assert torch.equal(two, one) and torch.equal(g_two, halves)
    assert {k: len(v) for k, v in split.items()} == {"_gather_parts": 2, "_scatter_parts": 1}


def _bits(x: torch.Tensor) -> torch.Tensor:
    """The values' bit patterns (signed zeros and NaN payloads told apart)."""
    return x.contiguous().view(torch.int32 if x.dtype == torch.float32 else torch.int64)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("align,padding", [(True, "zeros"), (False, "zeros"), (True, "border"),
                                           (False, "border")])
def test_vertex_corners_compiled_equal_the_tensor_form_to_the_bit(dtype, align, padding,
                                                                 monkeypatch):
    """The compiled pass from normalised coordinates to corners and weights against
    ``corners(vertex_coords(…))``, on random points inside and outside the grid and on
    the edges, NaN, ±inf, huge values and −0: the same lower corners and the same bits."""
    import baselines.interp as interp
    from baselines.interp import vertex_coords, vertex_corners

    calls = []
    kernel = interp._vertex_corners
    monkeypatch.setattr(interp, "_vertex_corners", lambda *a: (calls.append(1), kernel(*a))[1])
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
            ref_low, ref_w = corners(vertex_coords(picked, sizes[:d], align, padding))
            assert low.dtype == torch.long and w.dtype == dtype and low.shape == (20_000, d)
            assert torch.equal(low, ref_low) and torch.equal(_bits(w), _bits(ref_w))
    with torch_threads(1):
        vertex_corners(c, (4, 5, 6), align, padding)
    assert calls                                                  # the compiled pass ran


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_box_normalize_compiled_equals_the_tensor_form_to_the_bit(dtype, monkeypatch):
    g = torch.Generator().manual_seed(6)
    xyz = torch.randn(5000, 3, generator=g, dtype=dtype)
    t = torch.rand(5000, 1, generator=g)                         # float32 times, cast
    xyz[0, 0], xyz[1, 1], xyz[2, 2] = float("nan"), float("inf"), -0.0
    lo, hi = torch.tensor([-0.5, -0.75, -0.5]), torch.tensor([0.5, 0.25, 0.5])
    calls = []
    kernel = grids._box_normalize
    monkeypatch.setattr(grids, "_box_normalize", lambda *a: (calls.append(1), kernel(*a))[1])
    fast = grids.box_normalize(xyz, t, lo, hi)
    assert calls == [1]
    monkeypatch.setattr(grids, "AVAILABLE", False)
    slow = grids.box_normalize(xyz, t, lo, hi)
    assert fast.dtype == slow.dtype == dtype and torch.equal(_bits(fast), _bits(slow))
    assert fast[3:].abs().max() < 10                               # finite elsewhere


def test_interpolate_reads_the_named_columns_as_the_gathered_coordinates():
    """``axes`` reads the grid's coordinates off the columns of ``[N, D]`` instead of a
    gathered copy: the same values and the same grid gradient, to the bit; axes that do
    not fit the grid raise one error."""
    g = torch.Generator().manual_seed(7)
    grid = grids.channels_last(torch.randn(8, 9, 5, generator=g)).requires_grad_(True)
    coords = torch.rand(3000, 4, generator=g) * 2.2 - 1.1
    w = torch.randn(3000, 8, generator=g)
    outs = [grids.sample_points(grid, coords, True, "zeros", (3, 1)),
            grids.sample_points(grid, coords[:, [3, 1]], True, "zeros")]
    grads = [torch.autograd.grad((o * w).sum(), grid)[0] for o in outs]
    assert torch.equal(outs[0], outs[1]) and torch.equal(grads[0], grads[1])
    for axes in ((3,), (0, 4), (1, 2, 3)):
        with pytest.raises(InputError, match="coords"):
            interpolate(grid, coords, True, "zeros", axes)


@pytest.mark.skipif(numba_threads() < 2, reason="numba has one thread here")
def test_vertex_corners_split_between_two_threads_gives_the_same_bits(monkeypatch):
    import baselines.interp as interp

    calls = []
    kernel = interp._vertex_corners_parts
    monkeypatch.setattr(interp, "_vertex_corners_parts",
                        lambda *a: (calls.append(1), kernel(*a))[1])
    c = torch.rand(4 * GRAIN, 4, generator=torch.Generator().manual_seed(8)) * 2.4 - 1.2
    with torch_threads(1):
        one = interp.vertex_corners(c, (9, 7), False, "zeros", (3, 0))
    with torch_threads(2):
        two = interp.vertex_corners(c, (9, 7), False, "zeros", (3, 0))
    assert calls == [1]
    assert torch.equal(one[0], two[0]) and torch.equal(_bits(one[1]), _bits(two[1]))
    with pytest.raises(InputError, match="axes/sizes"):
        interp.vertex_corners(c, (9,), False, "zeros", (3, 0))
