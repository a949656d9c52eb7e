"""The compiled final level (``eventrecon.render.compiled_render``) against PyTorch's path.

PyTorch's :meth:`Renderer.forward` is the reference: the compiled loops must ask the field
on the same samples (the same count, so the same skips and stops) and give the same
colour, opacity and depth to float32 rounding, with and without the occupancy grid, with
misses, an annealed radius and without a fine level.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import Tensor

from eventrecon.fields.base import Field
from eventrecon.render import compiled_render
from eventrecon.render.compiled import numba_threads, parts
from eventrecon.render.samplers import pdf_bins, sample_pdf, stratified
from eventrecon.render.volume import Renderer, composite

pytestmark = pytest.mark.skipif(not compiled_render.AVAILABLE, reason="needs numba")

CYL = {"radius": 0.5, "y_min": -0.75, "y_max": 0.25}


class TwoBlobs(Field):
    """A moving soft blob and a static dense one (rays through it stop), with a colour
    that varies in space and time; zero density far from both."""

    def forward(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        moving = torch.cat([0.3 * (2 * t - 1), torch.full_like(t, -0.3), torch.zeros_like(t)], -1)
        dense = torch.tensor([0.0, -0.1, 0.2])
        sigma = (30.0 * torch.relu(0.04 - (xyz - moving).square().sum(-1))
                 + 40000.0 * torch.relu(0.01 - (xyz - dense).square().sum(-1)))
        return sigma, torch.sigmoid(4.0 * xyz + t)


def _rays(n: int, seed: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Rays from a ring at radius 2.5 towards the cylinder (a quarter aimed to miss it),
    random times and backgrounds."""
    g = torch.Generator().manual_seed(seed)
    ang = torch.rand(n, generator=g) * 6.2832
    o = torch.stack([2.5 * ang.cos(), torch.full((n,), -0.25), 2.5 * ang.sin()], -1)
    target = torch.stack([torch.rand(n, generator=g) - 0.5, torch.rand(n, generator=g) * 0.8
                          - 0.65, torch.rand(n, generator=g) - 0.5], -1) * 0.8
    target[: n // 4, 1] = -3.0                   # far above the cylinder
    d = target - o
    return (o, d / d.norm(dim=-1, keepdim=True), torch.rand(n, 1, generator=g),
            torch.rand(n, 3, generator=g))


def _renderer(skip: str, n_fine: int = 32, **kw) -> Renderer:
    r = Renderer(n_coarse=32, n_fine=n_fine, skip=skip, **CYL, **kw)
    if skip == "grid":
        for step in range(3):
            r.occupancy.update(lambda x, t: r.masked_density(TwoBlobs(), x, t),
                               torch.Generator().manual_seed(step))
    return r


def _both(r: Renderer, o: Tensor, d: Tensor, t: Tensor, bg: Tensor
          ) -> tuple[dict[str, Tensor], int, dict[str, Tensor], int]:
    """The final level by PyTorch's path and by the compiled one, and the samples each
    sent to the field."""
    field = TwoBlobs()
    with torch.no_grad():
        r.field_inputs = 0
        ref = r.forward(field, o, d, t, bg)[-1]
        n_ref, r.field_inputs = r.field_inputs, 0
        out = compiled_render.render_final(r, field, o, d, t, bg)
    assert out is not None
    return ref, n_ref, out, r.field_inputs


@pytest.mark.parametrize(("skip", "n_fine", "clip_scale"),
                         [("none", 32, 1.0), ("grid", 32, 1.0), ("grid", 0, 1.0),
                          ("none", 0, 1.0), ("grid", 32, 0.6), ("none", 32, 0.6)])
def test_same_samples_and_the_same_image_as_pytorchs_path(skip: str, n_fine: int,
                                                          clip_scale: float) -> None:
    r = _renderer(skip, n_fine, clip_scale=clip_scale)
    o, d, t, bg = _rays(600, 0)
    ref, n_ref, out, n_out = _both(r, o, d, t, bg)
    assert n_out == n_ref
    assert torch.allclose(out["rgb"], ref["rgb"], atol=2e-6, rtol=0)
    assert torch.allclose(out["opacity"], ref["opacity"], atol=2e-6, rtol=0)
    assert torch.allclose(out["depth"], ref["depth"], atol=1e-5, rtol=0)
    missed = slice(0, 150)
    assert torch.equal(out["rgb"][missed], bg[missed])
    assert torch.equal(out["opacity"][missed], torch.zeros(150))
    # the scene is not trivial: rays through the dense blob are opaque, others clear
    assert out["opacity"].max() > 0.999 and (out["opacity"][150:] < 1e-3).any()


def test_the_grid_and_the_stop_skip_samples_here_too() -> None:
    o, d, t, bg = _rays(600, 1)
    _, dense, _, _ = _both(_renderer("none"), o, d, t, bg)
    _, n_ref, _, n_out = _both(_renderer("grid"), o, d, t, bg)
    assert n_out == n_ref < dense / 3


def test_the_fine_samples_are_sample_pdfs_quantiles() -> None:
    g = torch.Generator().manual_seed(3)
    n, k, n_fine = 200, 24, 17
    near = torch.rand(n, generator=g)
    far = near + 0.5 + torch.rand(n, generator=g)
    s = stratified(near, far, k, perturb=False)
    sigma = torch.rand(n, k, generator=g) * 8 * (torch.rand(n, k, generator=g) > 0.4)
    sigma[:20] = 0.0                              # empty rays: the eps makes them uniform
    slot = np.arange(n * k, dtype=np.int64).reshape(n, k)
    s_f, stop_s = np.empty((n, n_fine), np.float32), np.empty(n, np.float32)
    compiled_render._fine(s.numpy(), far.numpy(), slot, sigma.reshape(-1).numpy(),
                          torch.linspace(0, 1, n_fine).numpy(), np.array([1e-6], np.float32),
                          np.array([1e-4], np.float32), np.empty(k, np.float32),
                          np.empty(k - 1, np.float32), s_f, stop_s)
    weights = composite(sigma, torch.zeros(n, k, 3), s, far, torch.zeros(n, 3))["weights"]
    ref = sample_pdf(*pdf_bins(s, weights), n_fine, deterministic=True)
    assert torch.allclose(torch.from_numpy(s_f), ref, atol=1e-5, rtol=0)
    # the stop: the end of the first step after which 1 − Σw < 1e-4, else far
    trans = 1.0 - weights.cumsum(-1)
    ends = torch.cat([s[:, 1:], far[:, None]], -1)
    first = (trans < 1e-4).float().argmax(-1)
    expect = torch.where((trans < 1e-4).any(-1), ends.gather(1, first[:, None])[:, 0], far)
    assert torch.equal(torch.from_numpy(stop_s), expect)


def test_gradients_or_a_non_float32_call_take_pytorchs_path() -> None:
    r = _renderer("grid")
    o, d, t, bg = _rays(64, 2)
    field = TwoBlobs()
    assert compiled_render.render_final(r, field, o, d, t, bg) is None   # grad mode on
    with torch.no_grad():
        assert compiled_render.render_final(r, field, o.double(), d.double(), t.double(),
                                            bg.double()) is None
        a = r.final_level(field, o, d, t, bg)
        b = r.forward(field, o, d, t, bg)[-1]
    assert torch.allclose(a["rgb"], b["rgb"], atol=2e-6, rtol=0)


def test_no_ray_meets_the_cylinder() -> None:
    r = _renderer("grid")
    o, d, t, bg = _rays(40, 4)
    o, d, t, bg = o[:10], d[:10], t[:10], bg[:10]        # all aimed above it
    with torch.no_grad():
        r.field_inputs = 0
        out = compiled_render.render_final(r, TwoBlobs(), o, d, t, bg)
    assert r.field_inputs == 0
    assert torch.equal(out["rgb"], bg) and torch.equal(out["depth"], torch.zeros(10))


@pytest.mark.skipif(numba_threads() < 2, reason="numba has one thread here")
def test_rays_split_between_threads_give_the_same_bits() -> None:
    r = _renderer("grid")
    o, d, t, bg = _rays(4096, 5)                  # ~3000 hits: two ranges of rays
    threads = torch.get_num_threads()
    outs = []
    try:
        for k in (1, 2):
            torch.set_num_threads(k)
            assert parts(3000, compiled_render._GRAIN) == k
            with torch.no_grad():
                outs.append(compiled_render.render_final(r, TwoBlobs(), o, d, t, bg))
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(outs[0][key], outs[1][key]) for key in outs[0])
