"""The renderer protocol: the module, the losses and the evaluation see only (view, pixel,
time) -> colour, opacity, depth. A representation that is not a volume (here a learnable
colour per view and time bin, "rendered" without any ray) trains through the unchanged
module and renders images through the protocol's default ``render_image``."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from integration import tiny_config
from torch import Tensor, nn

from eventrecon.common.errors import InputError
from eventrecon.data.batcher import Segment
from eventrecon.engine import build
from eventrecon.engine.losses import total_loss
from eventrecon.engine.module import EventNeRFModule, StepConfig, step_generator
from eventrecon.render.cameras import ring_rig
from eventrecon.render.renderer import Renderer
from eventrecon.render.volume import VolumeRenderer


class ViewColours(nn.Module):
    """A colour and an opacity logit per (view, time bin): no geometry at all."""

    def __init__(self, views: int, bins: int = 4) -> None:
        super().__init__()
        self.colour = nn.Parameter(torch.zeros(views, bins, 3))
        self.alpha = nn.Parameter(torch.zeros(views, bins))

    def param_groups(self, lr: float) -> list[dict]:
        return [{"params": list(self.parameters()), "lr": lr}]

    def callbacks(self) -> list:
        return []

    def regularization(self) -> None:
        return None

    def set_scene_box(self, lo, hi) -> None:
        return None


class FlatRenderer(Renderer):
    """One level: ``rgb = a·sigmoid(c[view, bin(t)]) + (1 − a)·bg``, ``a = sigmoid(α)``."""

    def forward(self, model: ViewColours, cams, view: Tensor, uv: Tensor, t: Tensor,
                bg: Tensor, perturb: bool = False, gen=None, copies: int = 1) -> list[dict]:
        bins = model.colour.shape[1]
        b = (t[:, 0] * bins).long().clamp(0, bins - 1)
        v = view.to(t.device)
        a = torch.sigmoid(model.alpha[v, b])
        rgb = a[:, None] * torch.sigmoid(model.colour[v, b]) + (1 - a[:, None]) * bg
        return [{"rgb": rgb, "opacity": a, "depth": torch.full_like(a, 2.0)}]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("data")


def test_a_renderer_without_rays_trains_through_the_unchanged_module(data_dir: Path) -> None:
    cfg = tiny_config(data_dir, "scene=blocks")
    ds = build.load_dataset(cfg)
    props = build.scene_properties(cfg, ds)
    volume = build.build_module(cfg, props, ds.splits["train"], Segment(0, 1000))
    model = ViewColours(volume.batcher.n_views)
    module = EventNeRFModule(model, FlatRenderer(), volume.batcher, volume.loss_cfg,
                             StepConfig(n_rays=96, lr=0.05))
    opt = torch.optim.Adam(model.parameters(), lr=0.05)

    def loss_at(step: int) -> Tensor:
        gen = step_generator(0, step)
        batch = module.batcher.sample(96, gen)
        levels = module.render_three(batch, gen)
        assert len(levels) == 1 and levels[0]["rgb_t0"].shape == (96, 3)
        return total_loss(levels, batch, module.loss_cfg, step)["loss"]

    fixed = [10_000 + i for i in range(4)]
    with torch.no_grad():
        before = float(sum(loss_at(s) for s in fixed))
    for step in range(60):
        loss = loss_at(step)
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        after = float(sum(loss_at(s) for s in fixed))
    assert after < 0.9 * before                  # 0.80 of it at seed 0
    assert float(model.colour.grad.abs().sum()) > 0


def test_the_default_render_image_renders_every_pixel_centre_through_forward() -> None:
    cams = ring_rig(2, 6, 4, radius=2.5, fov_deg=30)
    model = ViewColours(2)
    with torch.no_grad():
        model.colour[1, 2] = torch.tensor([2.0, 0.0, -2.0])
        model.alpha[1, 2] = 3.0
    img = FlatRenderer().render_image(model, cams, 1, 0.6, bg_image=0.25)
    a = torch.sigmoid(torch.tensor(3.0))
    expected = a * torch.sigmoid(torch.tensor([2.0, 0.0, -2.0])) + (1 - a) * 0.25
    assert img["rgb"].shape == (4, 6, 3) and img["opacity"].shape == (4, 6)
    assert torch.allclose(img["rgb"], expected.expand(4, 6, 3))
    assert torch.allclose(img["opacity"], a.expand(4, 6))


def test_the_volume_renderers_protocol_call_casts_the_rays_through_the_pixels() -> None:
    """``forward(view, uv, ...)`` is :meth:`render_rays` on ``cams.rays(view, uv)``, the
    rays computed once per block of ``copies``."""
    from eventrecon.fields import NeRFField

    torch.manual_seed(0)
    field = NeRFField(depth=2, width=16, skip=-1, pos_bands=2, time_bands=1, anneal_steps=0)
    cams = ring_rig(3, 16, 12, radius=2.5, fov_deg=40)
    g = torch.Generator().manual_seed(1)
    view = torch.randint(0, 3, (20,), generator=g)
    uv = torch.rand(20, 2, generator=g, dtype=torch.float64) * torch.tensor([16.0, 12.0])
    t = torch.rand(60, 1, generator=g)
    bg = torch.rand(60, 3, generator=g)
    renderer = VolumeRenderer(8, 8)
    got = renderer(field, cams, view.repeat(3), uv.repeat(3, 1), t, bg, copies=3)
    o, d = cams.rays(view, uv)
    ref = renderer.render_rays(field, o.repeat(3, 1), d.repeat(3, 1), t, bg, copies=3)
    for a, b in zip(got, ref):
        assert torch.equal(a["rgb"], b["rgb"]) and torch.equal(a["depth"], b["depth"])
    assert renderer.step_stats(60)["samples_per_ray"] > 0
    with pytest.raises(InputError, match="copies"):
        renderer(field, cams, view, uv, t[:20], bg[:20], copies=3)
