"""Clipping intervals, samplers and volume rendering, with known answers and bounds."""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor, nn

from eventrecon.common.errors import InputError
from eventrecon.fields.base import Field
from eventrecon.render.cameras import ring_rig
from eventrecon.render.clipping import Cylinder
from eventrecon.render.queries import padded_rows, query_field
from eventrecon.render.samplers import pdf_bins, sample_pdf, step_sizes, stratified
from eventrecon.render.volume import VolumeRenderer, composite, render_weights


class ConstantField(Field):
    """σ and colour constant everywhere (learnable, to check gradients)."""

    def __init__(self, sigma: float, rgb: tuple[float, float, float]) -> None:
        super().__init__()
        self.sigma = nn.Parameter(torch.tensor(float(sigma)))
        self.rgb = nn.Parameter(torch.tensor(rgb, dtype=torch.float32))

    def forward(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        n = xyz.shape[0]
        return self.sigma.expand(n), self.rgb.expand(n, 3)


class WallField(Field):
    """An opaque half-space ``x > x0`` of colour ``rgb`` (σ = ``sigma`` there, else 0)."""

    def __init__(self, x0: float, sigma: float, rgb: tuple[float, float, float]) -> None:
        super().__init__()
        self.x0, self.sigma_value = x0, sigma
        self.rgb = nn.Parameter(torch.tensor(rgb, dtype=torch.float32))
        self.calls = 0

    def forward(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        self.calls += xyz.shape[0]
        sigma = torch.where(xyz[:, 0] > self.x0, self.sigma_value, 0.0) * (1 + 0 * self.rgb[0])
        return sigma, self.rgb.expand(xyz.shape[0], 3)


def _ray(o: list[float], d: list[float]) -> tuple[Tensor, Tensor]:
    dt = torch.tensor([d], dtype=torch.float64)
    return torch.tensor([o], dtype=torch.float64), dt / dt.norm()


# ----------------------------------------------------------------------------- clipping

CYL = Cylinder(0.5, -0.75, 0.25)


@pytest.mark.parametrize(
    "o, d, scale, expected",
    [
        # Horizontal through the axis at y = -0.25: cylinder x in [-0.5, 0.5].
        ([-2, -0.25, 0], [1, 0, 0], 1.0, (1.5, 2.5)),
        ([-2, -0.25, 0], [1, 0, 0], 0.5, (1.75, 2.25)),
        # Chord at z = 0.49: half-length sqrt(0.25 - 0.49^2).
        ([-2, -0.25, 0.49], [1, 0, 0], 1.0,
         (2 - math.sqrt(0.25 - 0.49**2), 2 + math.sqrt(0.25 - 0.49**2))),
        # Parallel to the axis, downward (+y): slab y in [-0.75, 0.25] from y = -2.
        ([0.1, -2, 0.2], [0, 1, 0], 1.0, (1.25, 2.25)),
        # Exactly on the axis, from above the top cap.
        ([0.0, -2, 0.0], [0, 1, 0], 1.0, (1.25, 2.25)),
        # Parallel, upward (-y) from below the floor.
        ([0.1, 2, 0.2], [0, -1, 0], 1.0, (1.75, 2.75)),
        # Starting inside, along +x: exits the cylinder at x = 0.5.
        ([0, 0, 0], [1, 0, 0], 1.0, (0.0, 0.5)),
        # Diagonal through the top cap: enters through y = -0.75, exits through the side.
        ([0, -1.75, -1], [0, 1, 1], 1.0, (1.0 * math.sqrt(2), 1.5 * math.sqrt(2))),
    ],
)
def test_cylinder_interval_hand_computed(o, d, scale, expected) -> None:
    near, far, hit = CYL.ray_interval(*_ray(o, d), radius_scale=scale)
    assert bool(hit[0])
    assert near.item() == pytest.approx(expected[0], abs=1e-12)
    assert far.item() == pytest.approx(expected[1], abs=1e-12)


def test_cylinder_without_clipping_is_cut_by_the_unit_sphere() -> None:
    # r = 1, y in [-1, 1]: the sphere chord at y = -0.25 is 2 ± sqrt(1 - 0.0625).
    near, far, hit = Cylinder(1.0, -1.0, 1.0).ray_interval(*_ray([-2, -0.25, 0], [1, 0, 0]))
    half = math.sqrt(1 - 0.25**2)
    assert bool(hit[0]) and near.item() == pytest.approx(2 - half, abs=1e-12)
    assert far.item() == pytest.approx(2 + half, abs=1e-12)


@pytest.mark.parametrize(
    "o, d, scale",
    [
        ([-2, -0.25, 0.5], [1, 0, 0], 1.0),   # tangent: zero-length interval
        ([-2, -0.25, 0.0], [0, 0, 1], 1.0),   # passes beside the cylinder
        ([-2, -0.25, 0.0], [-1, 0, 0], 1.0),  # points away (s < 0 only)
        ([0.6, -2, 0.0], [0, 1, 0], 1.0),     # parallel to the axis, outside
        ([0.0, -0.25, -2], [0, 0, 1], 0.0),   # zero radius contains nothing
        ([0.0, -0.9, -2], [0, 0, 1], 1.0),    # above the slab (y < y_min), horizontal
        ([0.0, 0.0, 0.0], [0, 1, 0], 0.0),    # on the axis, zero radius
    ],
)
def test_cylinder_misses_are_flagged_with_finite_equal_ends(o, d, scale) -> None:
    near, far, hit = CYL.ray_interval(*_ray(o, d), radius_scale=scale)
    assert not bool(hit[0])
    assert near.item() == far.item() == 0.0


def test_cylinder_interval_matches_brute_force_march() -> None:
    gen = torch.Generator().manual_seed(1)
    n = 256
    dirs = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    origins = -2.0 * dirs + 0.6 * torch.randn(n, 3, generator=gen, dtype=torch.float64)
    origins[:32] = 0.3 * torch.rand(32, 3, generator=gen, dtype=torch.float64) - 0.15
    near, far, hit = CYL.ray_interval(origins, dirs, radius_scale=0.8)
    step = 4e-4
    s = torch.arange(0, 6.0, step, dtype=torch.float64)  # every origin is within 5 of 0
    p = origins[:, None, :] + s[None, :, None] * dirs[:, None, :]
    ins = CYL.inside(p, 0.8) & (p.norm(dim=-1) <= 1.0)
    any_in = ins.any(dim=1)
    first = torch.where(any_in, s[ins.float().argmax(dim=1)], 0.0)
    last = torch.where(any_in, s[(ins.float() * torch.arange(s.numel())).argmax(dim=1)], 0.0)
    assert int(any_in.sum()) > 80 and bool((~any_in).any())  # both cases present
    long_enough = (far - near) > 10 * step
    assert torch.equal(hit[long_enough | ~any_in], any_in[long_enough | ~any_in])
    assert float((near - first)[any_in].abs().max()) <= step
    assert float((far - last)[any_in].abs().max()) <= step


def test_cylinder_rejects_bad_parameters() -> None:
    with pytest.raises(InputError, match="radius"):
        Cylinder(radius=0.0)
    with pytest.raises(InputError, match="y_min"):
        Cylinder(y_min=0.5, y_max=0.0)


# ----------------------------------------------------------------------------- samplers

def test_stratified_one_sample_per_authors_cell_and_reproducible() -> None:
    """The authors' placement: points z_i = near + i·Δ, Δ = (far − near)/(n − 1), each
    jittered uniformly in [z_i − Δ/2, z_i + Δ/2] ∩ [near, far] (half-wide end cells)."""
    near, far = torch.tensor([0.5, 1.0, 2.0]), torch.tensor([1.5, 4.0, 2.0 + 1e-6])
    gen = torch.Generator().manual_seed(3)
    s = stratified(near, far, 16, perturb=True, gen=gen)
    step = ((far - near) / 15)[:, None]
    z = near[:, None] + step * torch.arange(16.0)
    lo, hi = (z - step / 2).maximum(near[:, None]), (z + step / 2).minimum(far[:, None])
    tol = 1e-6
    assert bool(((s >= lo - tol) & (s <= hi + tol)).all())
    s2 = stratified(near, far, 16, perturb=True, gen=torch.Generator().manual_seed(3))
    assert torch.equal(s, s2)
    assert torch.allclose(stratified(near[:1], far[:1], 5, perturb=False),
                          torch.tensor([[0.5, 0.75, 1.0, 1.25, 1.5]]))
    # the jitter is uniform in each cell: an end cell's samples average a quarter step
    # inside it (the authors' comment), an inner cell's its point
    many = stratified(torch.zeros(20000), torch.ones(20000), 5, True, gen)
    mean = many.mean(0)
    spread = 0.25 / math.sqrt(12 * 20000)          # cell width 1/4, uniform
    assert abs(mean[0].item() - 1 / 16) < 5 * spread and abs(mean[4].item() - 15 / 16) < 5 * spread
    assert abs(mean[2].item() - 0.5) < 10 * spread
    with pytest.raises(InputError, match="n"):
        stratified(near, far, 1, perturb=False)


def test_importance_samples_follow_the_weights() -> None:
    gen = torch.Generator().manual_seed(0)
    m = 20
    bins = torch.cumsum(torch.rand(2, m + 1, generator=gen) + 0.05, dim=-1)
    weights = torch.rand(2, m, generator=gen) ** 3
    weights[:, 5] = 0.0
    p = (weights + 1e-6) / (weights + 1e-6).sum(-1, keepdim=True)

    # Deterministic: u = k/(n − 1), so bin j receives (n − 1) p_j samples up to ±1.
    n = 1001
    s = sample_pdf(bins, weights, n, deterministic=True)
    inside_bin = (s[:, None, :] >= bins[:, :-1, None]) & (s[:, None, :] < bins[:, 1:, None])
    counts = inside_bin.sum(-1).float()  # [2, m]; u = 1 lands on the last edge itself
    counts[:, -1] += (s == bins[:, -1:]).sum(-1)
    assert float((counts - (n - 1) * p).abs().max()) <= 1.0 + 1e-6

    # Random draws: chi-square goodness of fit (df = 19, p = 0.999 quantile 43.8).
    n = 100_000
    s = sample_pdf(bins, weights, n, deterministic=False, gen=gen)
    assert bool((s[:, 1:] >= s[:, :-1]).all())
    for r in range(2):
        idx = torch.searchsorted(bins[r].contiguous(), s[r].contiguous(), right=True) - 1
        counts = torch.bincount(idx.clamp(0, m - 1), minlength=m).double()
        expected = n * p[r].double()
        keep = expected > 5
        chi2 = float(((counts - expected) ** 2 / expected)[keep].sum())
        assert chi2 < 43.8
        assert int(counts[5]) <= n * 1e-3  # the empty bin gets only the eps share

    # Within a bin the samples are uniform: the mean of samples in bin 0 is its centre.
    one = torch.tensor([[0.0, 1.0, 3.0]])
    s = sample_pdf(one, torch.tensor([[0.0, 1.0]]), 20000, deterministic=False, gen=gen, eps=0)
    assert float(s.min()) >= 1.0 and float(s.mean()) == pytest.approx(2.0, abs=0.02)


def test_importance_sampling_of_all_zero_weights_is_uniform() -> None:
    bins = torch.linspace(0, 1, 9).expand(1, 9)
    s = sample_pdf(bins, torch.zeros(1, 8), 9, deterministic=True)
    assert torch.allclose(s, torch.arange(9.0) / 8, atol=1e-6)


def test_step_sizes_are_the_authors_forward_differences_and_the_fine_histogram_too() -> None:
    s = torch.sort(torch.rand(4, 10), dim=-1).values * 2 + 1
    far = torch.full((4,), 3.0)
    delta = step_sizes(s, far)
    assert torch.allclose(delta[:, :-1], s[:, 1:] - s[:, :-1])
    assert torch.allclose(delta[:, -1], far - s[:, -1])
    assert torch.allclose(delta.sum(-1), far - s[:, 0])
    w = torch.rand(4, 10)
    bins, inner = pdf_bins(s, w)
    assert torch.allclose(bins, 0.5 * (s[:, 1:] + s[:, :-1])) and torch.equal(inner, w[:, 1:-1])
    with pytest.raises(InputError, match="n_coarse"):
        pdf_bins(s[:, :2], w[:, :2])


# ----------------------------------------------------------------------------- compositing

def test_constant_slab_transmittance_is_exp_minus_sigma_d() -> None:
    sigma = torch.full((3, 50), 2.0)
    delta = torch.rand(3, 50) * 0.04
    _, t_last = render_weights(sigma, delta)
    assert torch.allclose(t_last, torch.exp(-2.0 * delta.sum(-1)), atol=1e-5, rtol=0)
    # Through the renderer: the clipped interval of the axis ray is [1.5, 2.5] (d = 1).
    o, d = _ray([-2, -0.25, 0], [1, 0, 0])
    # The authors' quadrature integrates from the first sample to far: τ = 2 (2.5 − s_0).
    field = ConstantField(2.0, (0.2, 0.4, 0.6))
    levels = VolumeRenderer(32, 16).render_rays(field, o.float(), d.float(), torch.zeros(1, 1),
                              torch.ones(1, 3), perturb=True,
                              gen=torch.Generator().manual_seed(0))
    for level in levels:
        trans = math.exp(-2.0 * (2.5 - level["s"][0, 0].item()))
        assert level["opacity"].item() == pytest.approx(1 - trans, abs=1e-5)
        expected = (1 - trans) * torch.tensor([0.2, 0.4, 0.6]) + trans
        assert torch.allclose(level["rgb"][0], expected, atol=1e-5)
    # without jitter the first sample is near itself: exactly exp(−2)
    level = VolumeRenderer(32, 16).render_rays(field, o.float(), d.float(), torch.zeros(1, 1),
                                               torch.ones(1, 3))[1]
    assert level["opacity"].item() == pytest.approx(1 - math.exp(-2.0), abs=1e-5)


def test_partial_slab_within_one_cell() -> None:
    # Density 3 for x > 0 only: transmittance exp(-3 * 0.5) up to one cell of error.
    o, d = _ray([-2, -0.25, 0], [1, 0, 0])
    levels = VolumeRenderer(64, 0).render_rays(WallField(0.0, 3.0, (1, 1, 1)), o.float(), d.float(),
                             torch.zeros(1, 1), torch.zeros(1, 3))
    cell = 1.0 / 63
    assert abs(levels[0]["opacity"].item() - (1 - math.exp(-1.5))) <= 3 * math.exp(-1.5) * cell


def test_opaque_wall_gives_its_colour_and_depth() -> None:
    o, d = _ray([-2, -0.25, 0], [1, 0, 0])
    o, d = o.float().expand(4, 3), d.float().expand(4, 3)
    field = WallField(0.1, 1e6, (0.2, 0.4, 0.6))
    coarse, fine = VolumeRenderer(64, 128).render_rays(field, o, d, torch.zeros(4, 1),
                                                       torch.ones(4, 3),
                                     perturb=True, gen=torch.Generator().manual_seed(0))
    # Depth is the first sample behind the wall: the 64 coarse points are 1/63 apart and
    # each is jittered by up to half that, so coarse gaps are at most 2/63. The fine
    # samples fill the one cell holding all the weight, which starts at most half a gap
    # (1/63) behind the wall, with 128 samples.
    for level, tol in ((coarse, 2.0 / 63), (fine, 1.0 / 63 + 2.0 / 63 / 128)):
        assert torch.allclose(level["rgb"], torch.tensor([0.2, 0.4, 0.6]).expand(4, 3), atol=1e-6)
        assert torch.allclose(level["opacity"], torch.ones(4))
        assert float((level["depth"].detach() - 2.1).abs().max()) <= tol


def test_one_parameter_set_for_both_levels_and_reuse_is_exact() -> None:
    field = _SmoothField()
    renderer = VolumeRenderer(16, 24)
    assert len(list(renderer.parameters())) == 0
    o, d = _ray([-2, -0.25, 0.1], [1, 0.05, -0.02])
    o, d = o.float(), d.float()
    coarse, fine = renderer.render_rays(field, o, d, torch.full((1, 1), 0.3), torch.zeros(1, 3),
                            perturb=True, gen=torch.Generator().manual_seed(2))
    grads = []
    for level in (coarse, fine):
        field.zero_grad()
        level["rgb"].sum().backward(retain_graph=True)
        grads.append(torch.cat([p.grad.reshape(-1) for p in field.parameters()]))
    assert float(grads[0].abs().sum()) > 0 and float(grads[1].abs().sum()) > 0
    assert not torch.allclose(grads[0], grads[1])
    # Reference for the fine level: evaluate the field afresh at all its samples.
    s = fine["s"]
    near, far, _ = renderer.cylinder.ray_interval(o, d)
    pts = (o[:, None] + s[..., None] * d[:, None]).reshape(-1, 3)
    sigma, rgb = field(pts, torch.full((pts.shape[0], 1), 0.3))
    ref = composite(sigma[None], rgb[None], s, far, torch.zeros(1, 3))
    assert torch.allclose(ref["rgb"], fine["rgb"], atol=1e-6)
    assert torch.allclose(ref["depth"], fine["depth"], atol=1e-6)


class _SmoothField(Field):
    """A small smooth learnable field (Gaussian blob) for gradient tests."""

    def __init__(self) -> None:
        super().__init__()
        self.centre = nn.Parameter(torch.tensor([0.0, -0.25, 0.0]))
        self.scale = nn.Parameter(torch.tensor(5.0))
        self.colour = nn.Linear(4, 3)

    def forward(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        sigma = self.scale * torch.exp(-((xyz - self.centre) ** 2).sum(-1) / 0.05)
        return sigma, torch.sigmoid(self.colour(torch.cat([xyz, t], -1)))


# ----------------------------------------------------------------------------- hard cases

def test_extreme_density_and_tiny_steps_are_finite() -> None:
    sigma = torch.tensor([[0.0, 1e6, 1e6, 3.0], [1e6, 1e6, 1e6, 1e6], [0.0, 0.0, 0.0, 0.0],
                          [1e6, 0.0, 5.0, 1e6]], requires_grad=True)
    delta = torch.tensor([[1e-8, 1e-8, 1e-8, 1e-8], [1.0, 1.0, 1.0, 1.0], [1.0, 0.5, 1.0, 1.0],
                          [1e-8, 0.0, 1e-8, 2.0]])
    rgb = torch.rand(4, 4, 3, requires_grad=True)
    s = torch.cat([torch.zeros(4, 1), delta.cumsum(-1)[:, :-1]], -1)   # steps = delta
    out = composite(sigma, rgb, s, delta.sum(-1), torch.ones(4, 3))
    (out["rgb"].sum() + out["depth"].sum() + out["opacity"].sum()).backward()
    for v in (out["rgb"], out["opacity"], out["depth"], sigma.grad, rgb.grad):
        assert bool(torch.isfinite(v).all())
    assert bool((out["rgb"] >= 0).all() and (out["rgb"] <= 1).all())
    assert bool((out["opacity"] >= 0).all() and (out["opacity"] <= 1).all())
    # sigma * delta = 1e-2 per step on the first ray, 1e6 on the second, 0 on the third.
    assert out["opacity"][0].item() == pytest.approx(1 - math.exp(-0.02 - 3e-8), rel=1e-4)
    assert out["opacity"][1].item() == 1.0 and out["opacity"][2].item() == 0.0
    assert torch.equal(out["rgb"][2], torch.ones(3))


def test_renderer_hard_rays_are_finite_and_missed_rays_show_background() -> None:
    o = torch.tensor([[-2, -0.25, 0], [0.1, -2, 0.2], [0.0, -0.25, -2.0], [-2, -0.25, 0.5],
                      [0.0, -0.25, 0.0], [5.0, 5.0, 5.0]])
    d = torch.tensor([[1.0, 0, 0], [0, 1, 0], [1.0, 0, 0], [1.0, 0, 0], [0, -1.0, 0],
                      [0, 0, 1.0]])
    bg = torch.rand(6, 3)
    missed = torch.tensor([False, False, True, True, False, True])
    renderer = VolumeRenderer(16, 16)
    for sigma in (1e6, 0.0, 1.0):
        field = ConstantField(sigma, (1.0, 1.0, 1.0))
        levels = renderer.render_rays(field, o, d, torch.rand(6, 1), bg, perturb=True,
                          gen=torch.Generator().manual_seed(0))
        loss = sum(lv["rgb"].sum() + lv["opacity"].sum() for lv in levels)
        loss.backward()
        for lv in levels:
            for key in ("rgb", "opacity", "depth"):
                assert bool(torch.isfinite(lv[key]).all())
            assert bool((lv["rgb"] >= 0).all() and (lv["rgb"] <= 1).all())
            assert bool((lv["opacity"] >= 0).all() and (lv["opacity"] <= 1).all())
            assert torch.equal(lv["rgb"][missed], bg[missed])
            assert torch.equal(lv["opacity"][missed], torch.zeros(3))
            if sigma == 0.0:
                assert torch.allclose(lv["rgb"], bg, atol=1e-7)
        assert all(bool(torch.isfinite(p.grad).all()) for p in field.parameters())


def test_no_ray_hits_still_backpropagates_zero_gradients() -> None:
    field = ConstantField(1.0, (0.5, 0.5, 0.5))
    renderer = VolumeRenderer(8, 8, clip_scale=0.0)  # the start of a cylinder-annealing schedule
    o, d = _ray([-2, -0.25, 0], [1, 0, 0])
    bg = torch.full((1, 3), 0.3)
    levels = renderer.render_rays(field, o.float(), d.float(), torch.zeros(1, 1), bg)
    assert len(levels) == 2 and torch.equal(levels[-1]["rgb"], bg)
    sum(lv["rgb"].sum() for lv in levels).backward()
    assert float(field.sigma.grad) == 0.0


def test_missed_rays_are_not_sent_to_the_field() -> None:
    field = WallField(0.0, 1.0, (1, 1, 1))
    o, d = _ray([-2, -0.25, 0], [1, 0, 0])
    o2, d2 = _ray([-2, -0.25, 0], [0, 0, 1])
    renderer = VolumeRenderer(8, 4, query_buckets=0)
    renderer.render_rays(field, torch.cat([o, o2]).float(), torch.cat([d, d2]).float(),
             torch.zeros(2, 1), torch.zeros(2, 3))
    assert field.calls == 8 + 4 and renderer.field_inputs == 8 + 4


def test_render_image_matches_forward_on_the_same_rays() -> None:
    cams = ring_rig(2, 12, 9, radius=2.5, fov_deg=30)
    field = _SmoothField()
    renderer = VolumeRenderer(16, 16, chunk=40)
    img = renderer.render_image(field, cams, 1, 0.5, bg_image=0.25)
    o, d = cams.image_rays(1)
    ref = renderer.render_rays(field, o, d, torch.full((o.shape[0], 1), 0.5),
                               torch.full((o.shape[0], 3), 0.25))
    assert img["rgb"].shape == (9, 12, 3) and img["depth"].shape == (9, 12)
    assert torch.allclose(img["rgb"].reshape(-1, 3), ref[-1]["rgb"], atol=1e-6)
    assert float(img["opacity"].max()) > 0.5  # the blob is in view
    assert torch.allclose(img["rgb"][0, 0], torch.full((3,), 0.25))  # corner misses
    with pytest.raises(InputError, match="bg_image"):
        renderer.render_image(field, cams, 0, 0.5, bg_image=torch.zeros(4, 4, 3))


def test_images_render_under_the_runs_mixed_precision_and_fp32_otherwise() -> None:
    """``image_dtype`` bf16: the field's matmuls run in bf16 on a CPU (rgb within bf16's
    rounding of the fp32 image, returned as float32); ``None`` and fp16 (emulated on a
    CPU): fp32, bit for bit."""
    from eventrecon.fields import NeRFField

    torch.manual_seed(0)
    field = NeRFField(depth=2, width=32, skip=-1, remap_width=32, colour_width=16,
                      anneal_steps=0)
    dtypes: list[torch.dtype] = []
    field.register_forward_hook(lambda _m, _i, out: dtypes.append(out[0].dtype))
    cams = ring_rig(2, 12, 9, radius=2.5, fov_deg=30)
    renderer = VolumeRenderer(16, 16)
    images = {}
    for dtype in (None, torch.float16, torch.bfloat16):
        dtypes.clear()
        renderer.image_dtype = dtype
        images[dtype] = renderer.render_image(field, cams, 1, 0.5, bg_image=0.25)["rgb"]
        assert images[dtype].dtype == torch.float32
        assert set(dtypes) == {torch.bfloat16 if dtype == torch.bfloat16 else torch.float32}
    assert torch.equal(images[None], images[torch.float16])
    diff = float((images[torch.bfloat16] - images[None]).abs().max())
    assert 0 < diff < 1e-2                            # bf16 keeps 8 bits of mantissa


def test_renders_without_autograd_query_the_field_in_blocks_of_query_rows() -> None:
    """``query_rows`` caps the rows of every field call of a full-image render (the
    same image up to rounding); a call under autograd is never split."""
    from eventrecon.fields import NeRFField

    torch.manual_seed(0)
    field = NeRFField(depth=2, width=32, skip=-1, remap_width=32, colour_width=16,
                      anneal_steps=0)
    seen: list[int] = []
    field.register_forward_hook(lambda _m, inputs, _o: seen.append(int(inputs[0].shape[0])))
    cams = ring_rig(2, 12, 9, radius=2.5, fov_deg=30)
    images = {}
    for rows in (0, 100):
        seen.clear()
        renderer = VolumeRenderer(16, 16, chunk=4096, query_rows=rows)
        images[rows] = renderer.render_image(field, cams, 1, 0.5, bg_image=0.25)["rgb"]
        calls = list(seen)
        if rows:
            assert max(calls) <= padded_rows(100, 8) == 128 and len(calls) > 4
        else:
            assert max(calls) > 1000                 # one call per level of the chunk
    assert torch.allclose(images[0], images[100], atol=1e-6)
    seen.clear()
    o, d = cams.image_rays(1)
    VolumeRenderer(16, 16, query_rows=100).render_rays(field, o, d,
                                                       torch.full((o.shape[0], 1), 0.5),
                                     torch.full((o.shape[0], 3), 0.25))
    assert max(seen) > 1000                          # autograd: one call, never split
    with pytest.raises(InputError, match="query_rows"):
        VolumeRenderer(16, 16, query_rows=-1)


def test_random_draws_come_from_the_generators_device_and_move_to_the_rays() -> None:
    """A CPU ``(seed, step)`` generator with rays on another device (a GPU in training):
    the draws are made on the CPU and moved, identical to the CPU result. ``meta`` stands
    in for the GPU here (no GPU in CI): no numbers, but the devices must line up."""
    from eventrecon.render.samplers import uniform

    gen = torch.Generator().manual_seed(3)
    cpu = uniform((4, 5), gen, torch.empty(0, dtype=torch.float64))
    again = uniform((4, 5), torch.Generator().manual_seed(3), torch.empty(0, device="meta"))
    assert again.device.type == "meta" and again.shape == (4, 5)
    assert cpu.dtype == torch.float64 and torch.equal(
        cpu, uniform((4, 5), torch.Generator().manual_seed(3), torch.empty(0, dtype=torch.float64)))
    near, far = torch.zeros(4, device="meta"), torch.ones(4, device="meta")
    assert stratified(near, far, 8, True, torch.Generator().manual_seed(0)).device.type == "meta"


def test_padded_rows_repeat_few_sizes_and_waste_at_most_one_step() -> None:
    sizes = [padded_rows(m, 8) for m in range(1, 20001)]
    assert all(r >= m and r % 64 == 0 for m, r in zip(range(1, 20001), sizes))
    # at most one geometric step (2^(1/8): 9.05 % more) and the rounding to 64 rows
    assert all(r <= m * 2 ** (1 / 8) + 64 for m, r in zip(range(1, 20001), sizes))
    assert len(set(sizes[1999:3999])) <= 9           # m in [2000, 4000): one octave
    assert padded_rows(3000, 0) == 3000 and padded_rows(0, 8) == 0


def test_padded_field_queries_give_the_same_values_and_gradients() -> None:
    from eventrecon.fields import NeRFField

    torch.manual_seed(0)
    field = NeRFField(depth=2, width=32, skip=-1, remap_width=32, colour_width=16,
                      anneal_steps=0)
    x, t = torch.rand(1000, 3) - 0.5, torch.rand(1000, 1)
    seen: list[int] = []
    field.register_forward_hook(lambda _m, inputs, _o: seen.append(int(inputs[0].shape[0])))
    grads = []
    for per_octave in (0, 8):
        field.zero_grad()
        sigma, rgb = query_field(field, x, t, per_octave)
        assert sigma.shape == (1000,) and rgb.shape == (1000, 3)
        (sigma.square().sum() + rgb.sum()).backward()
        grads.append((sigma.detach(), rgb.detach(),
                      [p.grad.clone() for p in field.parameters() if p.grad is not None]))
    assert seen == [1000, 1024]                      # the field really saw padded rows
    (s0, c0, g0), (s8, c8, g8) = grads
    assert torch.allclose(s0, s8, atol=1e-6) and torch.allclose(c0, c8, atol=1e-6)
    assert len(g0) == len(g8) > 0
    # the same sums over 1000 vs 1024 rows (24 of them cut off) round differently in fp32,
    # by the CPU's blocking: up to ~1e-7 of the largest entry (3e-5 of 183 on one Xeon);
    # the 24 repeated rows, if they leaked in, would move the gradients by ~2 % of it
    assert all(torch.allclose(a, b, rtol=1e-5, atol=1e-5 * float(a.abs().max()))
               for a, b in zip(g0, g8))


class _StaticBlob(Field):
    """A time-independent Gaussian blob with a position-dependent colour."""

    def forward(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        sigma = 8.0 * torch.exp(-((xyz - torch.tensor([0.0, -0.25, 0.0])) ** 2).sum(-1) / 0.05)
        return sigma, torch.sigmoid(3.0 * xyz)


def test_copies_of_a_ray_share_coarse_samples_and_draw_their_own_fine_ones() -> None:
    # 16 rays, 4 of them missing the cylinder, each rendered at three times (t0, t1, t_ref)
    offsets = torch.linspace(-0.1, 0.1, 12)
    o = torch.stack([torch.full((12,), -2.0), -0.25 + offsets, offsets.flip(0)], -1)
    d = torch.tensor([[1.0, 0.0, 0.0]]).expand(12, 3)
    o = torch.cat([o, torch.tensor([[3.0, 3.0, 3.0]] * 4)])
    d = torch.cat([d, torch.tensor([[1.0, 0.0, 0.0]] * 4)])
    t = torch.rand(48, 1, generator=torch.Generator().manual_seed(1))
    renderer = VolumeRenderer(n_coarse=16, n_fine=16)
    coarse, fine = renderer.render_rays(_StaticBlob(), o.repeat(3, 1), d.repeat(3, 1), t,
                                        torch.ones(48, 3),
                            perturb=True, gen=torch.Generator().manual_seed(2), copies=3)
    c = coarse["rgb"].reshape(3, 16, 3)
    assert torch.equal(coarse["s"].reshape(3, 16, -1)[1], coarse["s"].reshape(3, 16, -1)[0])
    # a static field renders every copy alike at the coarse level: no noise in L_event there
    assert float((c[1] - c[0]).abs().max()) == 0.0 and float((c[2] - c[0]).abs().max()) == 0.0
    assert float(coarse["opacity"][:12].min()) > 0.05   # the rays do cross the blob
    # the fine samples are each copy's own draws from the shared coarse weights
    f_s = fine["s"].reshape(3, 16, -1)[:, :12]
    assert float((f_s[1] - f_s[0]).abs().max()) > 1e-3
    # without copies each render draws its own coarse jitter
    alone, _ = renderer.render_rays(_StaticBlob(), o.repeat(3, 1), d.repeat(3, 1), t,
                                    torch.ones(48, 3),
                        perturb=True, gen=torch.Generator().manual_seed(2))
    a = alone["rgb"].reshape(3, 16, 3)
    assert float((a[1] - a[0]).abs().max()) > 1e-4
    with pytest.raises(InputError, match="copies"):
        stratified(torch.zeros(5), torch.ones(5), 4, True, copies=3)
