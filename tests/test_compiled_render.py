"""The compiled renderer (``eventrecon.render.compiled_render``) against PyTorch's passes.

``Renderer(compiled=False)`` is the reference: the compiled loops must ask the field on
the same samples (the same count, so the same skips and stops), draw the same random
samples, and give both levels' colour, opacity, depth and weights, and the gradients of a
loss on them, to float32 rounding, with and without the occupancy grid, with misses, an
annealed radius, several copies of a ray and without a fine level.
"""

from __future__ import annotations

from unittest import mock

import numpy as np
import pytest
import torch
from torch import Tensor, nn

from eventrecon.fields.base import Field
from eventrecon.render import compiled_render, composite_rows
from eventrecon.render.compiled import numba_threads, parts
from eventrecon.render.samplers import pdf_bins, sample_pdf, stratified, uniform
from eventrecon.render.volume import Renderer, composite

pytestmark = pytest.mark.skipif(not compiled_render.AVAILABLE, reason="needs numba")

CYL = {"radius": 0.5, "y_min": -0.75, "y_max": 0.25}
#: Tolerances. The fine samples' distances agree to float32 rounding, except where a
#: histogram bin holds almost no weight: there the inverse CDF divides by a difference of
#: nearly equal CDF values, whose last bit depends on the order of a sum (up to 2e-5 of
#: a distance here). A sample's weight moves with its step, so the weights get the most.
TOL = {"rgb": 5e-6, "opacity": 5e-6, "depth": 2e-5, "weights": 5e-5}
KEYS = tuple(TOL)


class TwoBlobs(Field):
    """A moving soft blob and a static dense one (rays through it stop), with a colour
    that varies in space and time; zero density far from both. Its scales and colour
    offset are parameters, so gradients can be compared."""

    def __init__(self) -> None:
        super().__init__()
        self.scale = nn.Parameter(torch.tensor([30.0, 40000.0]))
        self.offset = nn.Parameter(torch.tensor([0.1, -0.2, 0.3]))

    def forward(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        moving = torch.cat([0.3 * (2 * t - 1), torch.full_like(t, -0.3), torch.zeros_like(t)], -1)
        dense = torch.tensor([0.0, -0.1, 0.2])
        sigma = (self.scale[0] * torch.relu(0.04 - (xyz - moving).square().sum(-1))
                 + self.scale[1] * torch.relu(0.01 - (xyz - dense).square().sum(-1)))
        return sigma, torch.sigmoid(4.0 * xyz + t + self.offset)


def _rays(n: int, seed: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Rays from a ring at radius 2.5 towards the cylinder (the first quarter aimed to
    miss it), random times and backgrounds."""
    g = torch.Generator().manual_seed(seed)
    ang = torch.rand(n, generator=g) * 6.2832
    o = torch.stack([2.5 * ang.cos(), torch.full((n,), -0.25), 2.5 * ang.sin()], -1)
    target = torch.stack([torch.rand(n, generator=g) - 0.5, torch.rand(n, generator=g) * 0.8
                          - 0.65, torch.rand(n, generator=g) - 0.5], -1) * 0.8
    target[: n // 4, 1] = -3.0                   # far above the cylinder
    d = target - o
    return (o, d / d.norm(dim=-1, keepdim=True), torch.rand(n, 1, generator=g),
            torch.rand(n, 3, generator=g))


def _same_samples(a: Tensor, b: Tensor) -> None:
    """The two paths' sample distances: all but 0.1 % within 1e-5 and none more than
    1e-3 apart (the fine samples of nearly empty histogram bins, ``TOL``)."""
    diff = (a - b).abs()
    assert float((diff > 1e-5).float().mean()) <= 1e-3 and float(diff.max()) <= 1e-3


def _renderer(skip: str, n_fine: int = 32, compiled: bool = True, update: bool = True,
              **kw) -> Renderer:
    r = Renderer(n_coarse=32, n_fine=n_fine, skip=skip, compiled=compiled, **CYL, **kw)
    if skip == "grid" and update:
        for step in range(3):
            r.occupancy.update(lambda x, t: r.masked_density(TwoBlobs(), x, t),
                               torch.Generator().manual_seed(step))
    return r


def _render(r: Renderer, rays: tuple[Tensor, ...], grad: bool, perturb: bool = False,
            copies: int = 1, field: Field | None = None
            ) -> tuple[list[dict[str, Tensor]], int, list[Tensor]]:
    """Both levels, the samples sent to the field and (with ``grad``) the gradients of
    a loss on every output with respect to the field's parameters."""
    field = field or TwoBlobs()
    r.field_inputs = 0
    gen = torch.Generator().manual_seed(7) if perturb else None
    spy = mock.patch.object(compiled_render, "render_hit", wraps=compiled_render.render_hit)
    with torch.set_grad_enabled(grad), spy as hits:
        levels = r(field, *rays, perturb=perturb, gen=gen, copies=copies)
    assert hits.called == r.compiled          # the path asked for is the path taken
    with torch.set_grad_enabled(grad):
        grads = []
        if grad:
            w = torch.linspace(0.5, 1.5, rays[0].shape[0])
            loss = sum((lv["rgb"].sum(-1) * w).sum() + (lv["opacity"] * w).sum()
                       + 0.1 * lv["depth"].sum() for lv in levels)
            grads = list(torch.autograd.grad(loss, list(field.parameters())))
    return levels, r.field_inputs, grads


CASES = [("none", 32, 1.0), ("grid", 32, 1.0), ("grid", 0, 1.0), ("none", 0, 1.0),
         ("grid", 32, 0.6), ("none", 32, 0.6)]


@pytest.mark.parametrize("grad", [False, True], ids=["images", "training"])
@pytest.mark.parametrize(("skip", "n_fine", "clip_scale"), CASES)
def test_the_same_samples_levels_and_gradients_as_pytorchs_passes(
        skip: str, n_fine: int, clip_scale: float, grad: bool) -> None:
    rays = _rays(600, 0)
    ref, n_ref, g_ref = _render(_renderer(skip, n_fine, False, clip_scale=clip_scale), rays,
                                grad, perturb=grad)
    out, n_out, g_out = _render(_renderer(skip, n_fine, True, clip_scale=clip_scale), rays,
                                grad, perturb=grad)
    assert n_out == n_ref and len(out) == len(ref)
    assert torch.equal(out[0]["s"], ref[0]["s"])                  # the coarse draws
    for a, b in zip(out, ref):
        _same_samples(a["s"], b["s"])
        for key in KEYS:
            assert a[key].shape == b[key].shape
            assert torch.allclose(a[key], b[key], atol=TOL[key], rtol=0), key
    for a, b in zip(g_out, g_ref):
        assert torch.allclose(a, b, rtol=2e-4, atol=1e-6 * float(b.abs().max())), (a, b)
    fine = out[-1]
    assert torch.equal(fine["rgb"][:150], rays[3][:150])          # the misses
    assert torch.equal(fine["opacity"][:150], torch.zeros(150))
    # the scene is not trivial: rays through the dense blob are opaque, others clear
    assert fine["opacity"].max() > 0.999 and (fine["opacity"][150:] < 1e-3).any()


def test_copies_share_their_coarse_samples_and_draw_as_pytorch_does() -> None:
    o, d, t, bg = _rays(200, 3)
    rays = (o.repeat(3, 1), d.repeat(3, 1), torch.rand(600, 1), bg.repeat(3, 1))
    ref, n_ref, g_ref = _render(_renderer("grid", compiled=False), rays, True, True, copies=3)
    out, n_out, g_out = _render(_renderer("grid"), rays, True, True, copies=3)
    assert n_out == n_ref
    assert torch.equal(out[0]["s"], ref[0]["s"])
    _same_samples(out[1]["s"], ref[1]["s"])
    assert all(torch.allclose(a, b, rtol=2e-4, atol=1e-6 * float(b.abs().max()))
               for a, b in zip(g_out, g_ref))


def test_the_grid_and_the_stop_skip_samples_here_too() -> None:
    rays = _rays(600, 1)
    _, dense, _ = _render(_renderer("none"), rays, False)
    _, n_ref, _ = _render(_renderer("grid", compiled=False), rays, False)
    _, n_out, _ = _render(_renderer("grid"), rays, False)
    assert n_out == n_ref < dense / 3


def test_the_fine_samples_are_sample_pdfs_quantiles() -> None:
    g = torch.Generator().manual_seed(3)
    n, k, n_fine = 200, 24, 17
    near = torch.rand(n, generator=g)
    far = near + 0.5 + torch.rand(n, generator=g)
    s = stratified(near, far, k, perturb=False)
    sigma = torch.rand(n, k, generator=g) * 8 * (torch.rand(n, k, generator=g) > 0.4)
    sigma[:20] = 0.0                              # empty rays: the eps makes them uniform
    weights = composite(sigma, torch.zeros(n, k, 3), s, far, torch.zeros(n, 3))["weights"]
    bins, w = pdf_bins(s, weights)
    for deterministic in (True, False):           # sample_pdf's quantiles, or its draws
        if deterministic:
            u = torch.linspace(0, 1, n_fine).expand(n, n_fine).contiguous()
        else:
            u = uniform((n, n_fine), torch.Generator().manual_seed(9), s).sort(-1).values
        ref = sample_pdf(bins, w, n_fine, deterministic, torch.Generator().manual_seed(9))
        s_f, stop_s = torch.empty(n, n_fine), np.empty(n, np.float32)
        compiled_render._fine(s.numpy(), far.numpy(), weights.numpy(), u.numpy(),
                              np.array([1e-6], np.float32), np.array([1e-4], np.float32),
                              np.empty(k - 1, np.float32), s_f.numpy(), stop_s)
        assert torch.allclose(s_f, ref, atol=1e-5, rtol=0)
    # the stop: the end of the first step after which 1 − Σw < 1e-4, else far
    trans = 1.0 - weights.cumsum(-1)
    ends = torch.cat([s[:, 1:], far[:, None]], -1)
    first = (trans < 1e-4).float().argmax(-1)
    expect = torch.where((trans < 1e-4).any(-1), ends.gather(1, first[:, None])[:, 0], far)
    assert torch.equal(torch.from_numpy(stop_s), expect)


def test_composite_rows_gradient_against_finite_differences() -> None:
    g = torch.Generator().manual_seed(5)
    n, k = 6, 9
    s = torch.sort(torch.rand(n, k, generator=g), -1).values + 1.0
    far = s[:, -1] + 0.3
    slot = torch.arange(n * k).reshape(n, k)
    slot[0, 3] = slot[2, 0] = -1                  # samples without a row
    bg = torch.rand(n, 3, generator=g)
    mix = torch.rand(n * 5, generator=g, dtype=torch.float64)

    def loss(sig: Tensor, col: Tensor) -> Tensor:
        out = composite_rows.composite_rows(sig, col, s, slot, far, bg)
        flat = torch.cat([out["rgb"].reshape(-1), out["opacity"], 0.3 * out["depth"]])
        return (flat.double() * mix).sum()

    sig = (torch.rand(n * k, generator=g, dtype=torch.float64) * 4).requires_grad_()
    col = torch.rand(n * k, 3, generator=g, dtype=torch.float64).requires_grad_()
    g_sig, g_col = torch.autograd.grad(loss(sig, col), [sig, col])
    for i in torch.randperm(n * k, generator=g)[:12].tolist():
        for which, grad in ((0, g_sig.reshape(-1)), (1, g_col.reshape(-1))):
            x = (sig, col)[which].detach().reshape(-1)
            plus, minus = x.clone(), x.clone()
            plus[i] += 1e-2
            minus[i] -= 1e-2
            args = [sig.detach(), col.detach()]
            args[which] = plus.reshape(args[which].shape)
            f_plus = loss(*args)
            args[which] = minus.reshape(args[which].shape)
            f_minus = loss(*args)
            assert abs(float(f_plus - f_minus) / 2e-2 - float(grad[i])) < 2e-3


def test_composite_rows_keeps_what_compositing_again_would_give(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """With a gradient wanted the forward pass keeps each ray's float64 ``T`` and colour
    sums for the backward pass: the same bits as :func:`composite_rows._ray` gives ray by
    ray, the same outputs as without a gradient, and with nothing to give no backward."""
    g = torch.Generator().manual_seed(8)
    n, k = 40, 12
    s = torch.sort(torch.rand(n, k, generator=g), -1).values + 1.0
    far = s[:, -1] + 0.2
    slot = torch.arange(n * k).reshape(n, k)
    slot[::3, 2] = -1
    slot[1::4, 5] = -slot[1::4, 5] - 2              # masked rows
    sig, col = torch.rand(n * k, generator=g) * 6, torch.rand(n * k, 3, generator=g)
    bg = torch.rand(n, 3, generator=g)
    arrays = [x.numpy() for x in (s, slot, far, sig, col, bg)]
    outs = [np.empty((n, 3), np.float32), np.empty(n, np.float32), np.empty(n, np.float32),
            np.empty((n, k), np.float32)]
    after, sums = np.empty((n, k)), np.empty((n, 3))
    composite_rows._forward_parts(*arrays, composite_rows._tau_max(), *outs, after, sums, 2,
                                  True)
    row = np.empty(k)
    for r in range(n):
        c = composite_rows._ray(*arrays[:5], composite_rows._tau_max(), r, row)
        assert np.array_equal(after[r], row) and np.array_equal(sums[r], c[:3])
    plain = composite_rows.composite_rows(sig, col, s, slot, far, bg)
    sig_g, col_g = sig.clone().requires_grad_(), col.clone().requires_grad_()
    kept = composite_rows.composite_rows(sig_g, col_g, s, slot, far, bg)
    for key in ("rgb", "opacity", "depth", "weights"):
        assert torch.equal(plain[key], kept[key])
        assert np.array_equal(plain[key].numpy(), outs[("rgb", "opacity", "depth",
                                                        "weights").index(key)])
    def refuse(*args):                              # nothing was kept to read
        raise AssertionError("the backward loop ran")

    monkeypatch.setattr(composite_rows, "_backward_parts", refuse)
    s_g = s.clone().requires_grad_()                # only a gradient nobody gets here
    out = composite_rows.CompositeRows.apply(sig, col, s_g, slot, far, bg)
    assert torch.autograd.grad(out[0].sum(), s_g, allow_unused=True)[0] is None


@pytest.mark.skipif(numba_threads() < 2, reason="numba has one thread here")
def test_rays_split_between_threads_give_the_same_bits() -> None:
    rays = _rays(4096, 5)                        # ~3000 hits: two ranges of rays
    threads = torch.get_num_threads()
    outs = []
    try:
        for k in (1, 2):
            torch.set_num_threads(k)
            assert parts(3000, composite_rows.RAYS_PER_RANGE) == k
            outs.append(_render(_renderer("grid"), rays, True, perturb=True))
    finally:
        torch.set_num_threads(threads)
    (a, _, ga), (b, _, gb) = outs
    assert all(torch.equal(x[key], y[key]) for x, y in zip(a, b) for key in KEYS)
    assert all(torch.equal(x, y) for x, y in zip(ga, gb))


def test_no_ray_meets_the_cylinder() -> None:
    o, d, t, bg = (x[:10] for x in _rays(40, 4))  # all aimed above it
    levels, n, _ = _render(_renderer("grid"), (o, d, t, bg), False)
    assert n == 0
    assert torch.equal(levels[-1]["rgb"], bg) and torch.equal(levels[-1]["depth"], torch.zeros(10))


class NaNPatch(TwoBlobs):
    """TwoBlobs with a NaN density in one corner of the cylinder and a NaN colour in
    another, where the density is zero (weight 0: ``0 · NaN`` is still NaN)."""

    def forward(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        sigma, rgb = super().forward(xyz, t)
        sigma = torch.where(xyz[:, 0] > 0.3, torch.nan, sigma)
        rgb = torch.where((xyz[:, 0] < -0.3)[:, None], torch.nan, rgb)
        return sigma, rgb


@pytest.mark.parametrize(("skip", "clip_scale", "update"),
                         [("none", 1.0, True), ("grid", 1.0, True), ("none", 0.6, True),
                          ("grid", 1.0, False)])
@pytest.mark.parametrize("grad", [False, True], ids=["images", "training"])
def test_a_non_finite_field_makes_the_same_rays_nan(skip: str, clip_scale: float,
                                                    update: bool, grad: bool) -> None:
    """A diverging run must see its NaN: the compiled compositing keeps it as PyTorch's
    clamps, sums and masks do, also where a sample is asked but masked (outside an
    annealed cylinder, or behind a stop of the unasked grid: ``update=False``)
    (``tests/test_stability.py`` stops such a run by it)."""
    rays = _rays(600, 6)
    outs = []
    for compiled in (False, True):
        r = _renderer(skip, compiled=compiled, update=update, clip_scale=clip_scale)
        outs.append(_render(r, rays, grad, perturb=grad, field=NaNPatch())[0])
    for a, b in zip(*outs):
        for key in ("rgb", "opacity", "depth"):
            assert torch.equal(a[key].isnan(), b[key].isnan()), key
    assert outs[1][-1]["rgb"].isnan().any(-1).float().mean() > 0.1


def test_composite_rows_and_its_gradient_at_the_clamps() -> None:
    """Negative and huge densities (``τ`` clamped at ``TAU_MAX``), zero steps and colours
    outside [0, 1] (the output clamped): the values and the gradients of PyTorch's
    :func:`composite` under autograd."""
    g = torch.Generator().manual_seed(8)
    n, k = 64, 16
    s = torch.sort(torch.rand(n, k, generator=g), -1).values * 2 + 1
    s[:, 5] = s[:, 4]                               # a zero step
    far = s[:, -1] + 0.25
    sig = torch.randn(n * k, generator=g) * 3
    sig[::7] = 1e9                                  # τ = 1e9 · δ > TAU_MAX
    col = torch.rand(n * k, 3, generator=g) * 2 - 0.5
    bg = torch.rand(n, 3, generator=g) * 1.4 - 0.2
    slot = torch.arange(n * k).reshape(n, k)
    mix = [torch.randn(n, 3, generator=g), torch.randn(n, generator=g),
           torch.randn(n, generator=g)]
    outs, grads = [], []
    for compiled in (True, False):
        x, c = sig.clone().requires_grad_(), col.clone().requires_grad_()
        if compiled:
            out = composite_rows.composite_rows(x, c, s, slot, far, bg)
        else:
            out = composite(x.reshape(n, k), c.reshape(n, k, 3), s, far, bg)
        loss = sum((out[key] * m).sum() for key, m in zip(("rgb", "opacity", "depth"), mix))
        outs.append(out)
        grads.append(torch.autograd.grad(loss, [x, c]))
    for key in ("rgb", "opacity", "depth", "weights"):
        assert torch.allclose(outs[0][key], outs[1][key], atol=2e-6, rtol=1e-5), key
    assert ((outs[1]["rgb"] == 0) | (outs[1]["rgb"] == 1)).any()   # the clamp is active
    for a, b in zip(*grads):
        assert torch.allclose(a, b, atol=1e-5, rtol=1e-4)
        assert (a == 0).any() and (a != 0).any()
