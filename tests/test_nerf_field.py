"""Positional encoding, band annealing and the NeRF MLP field."""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from omegaconf import OmegaConf
from torch import nn

from eventrecon.common.errors import InputError
from eventrecon.fields import Field, NeRFField
from eventrecon.fields.encoding import BandAnnealing, PositionalEncoding, band_window
from eventrecon.render.volume import VolumeRenderer

CONF = str(Path(__file__).resolve().parents[1] / "conf" / "model" / "nerf.yaml")


def _reference_encoding(x: torch.Tensor, n_bands: int) -> torch.Tensor:
    """Slow float64 reference: raw input, then per band sin of all dims, cos of all dims."""
    x = x.double()
    parts = [x]
    for k in range(n_bands):
        parts += [torch.sin(2.0**k * x), torch.cos(2.0**k * x)]
    return torch.cat(parts, dim=-1)


def test_encoding_values_at_known_inputs() -> None:
    enc = PositionalEncoding(3, 3, anneal_steps=0)
    x = torch.tensor([[math.pi / 2, math.pi / 4, 0.0]])
    out = enc(x)[0]
    assert enc.out_dim == 21 and out.shape == (21,)
    assert torch.allclose(out[:3], x[0])
    # band 0: sin(pi/2, pi/4, 0), cos(...); band 1: sin(pi, pi/2, 0), cos(...)
    s2 = math.sqrt(0.5)
    expected_b0 = [1.0, s2, 0.0, 0.0, s2, 1.0]
    expected_b1 = [0.0, 1.0, 0.0, -1.0, 0.0, 1.0]
    expected_b2 = [0.0, 0.0, 0.0, 1.0, -1.0, 1.0]  # sin/cos of (2pi, pi, 0)
    assert torch.allclose(out[3:], torch.tensor(expected_b0 + expected_b1 + expected_b2),
                          atol=1e-6)


def test_encoding_at_and_beyond_the_unit_box_matches_float64() -> None:
    enc = PositionalEncoding(3, 14, anneal_steps=0)
    x = torch.tensor([[1.0, -1.0, 0.0], [1.0 + 1e-6, -1.0 - 1e-3, 1.5], [-1.0, 1.0, 1.0],
                      [-3.0, 2.0, 1e-7]], requires_grad=True)
    out = enc(x)
    out.sum().backward()
    assert bool(torch.isfinite(out).all()) and bool(torch.isfinite(x.grad).all())
    # 2^k x is exact in floating point, so even band 13 (8192 x) is exact to sin's ulp.
    assert float((out.detach().double() - _reference_encoding(x.detach(), 14)).abs().max()) < 2e-6
    # Time at the segment edges.
    t_enc = PositionalEncoding(1, 7, anneal_steps=0)
    t = torch.tensor([[0.0], [1.0]])
    assert float((t_enc(t).double() - _reference_encoding(t, 7)).abs().max()) < 1e-6


def test_annealing_window_turns_bands_on_in_order() -> None:
    enc = PositionalEncoding(2, 4, anneal_steps=400)
    x = torch.rand(5, 2) * 2 - 1
    # step 0: every band off, only the raw input is left.
    assert torch.equal(enc(x)[:, 2:], torch.zeros(5, 16))
    # step 150: alpha = 1.5 -> band 0 fully on, band 1 at w = 0.5, bands 2, 3 off.
    enc.set_progress(150)
    assert enc.window.tolist() == pytest.approx([1.0, 0.5, 0.0, 0.0], abs=1e-7)
    full = _reference_encoding(x, 4).float()
    out = enc(x)
    assert torch.allclose(out[:, :6], full[:, :6], atol=1e-6)
    assert torch.allclose(out[:, 6:10], 0.5 * full[:, 6:10], atol=1e-6)
    assert torch.equal(out[:, 10:], torch.zeros(5, 8))
    # band k is off up to alpha = k and on from alpha = k + 1 (alpha = 4 step / 400)
    for k in range(4):
        assert band_window(4, 100 * k, 400)[k] == 0.0
        assert band_window(4, 100 * (k + 1), 400)[k] == 1.0
        assert 0.0 < band_window(4, 100 * k + 30, 400)[k] < 1.0
    enc.set_progress(10_000)
    assert torch.allclose(enc(x), full, atol=1e-6)
    # the window is a checkpointed buffer
    assert "window" in enc.state_dict()


def test_a_window_of_ones_is_skipped_exactly_and_a_loaded_window_is_applied() -> None:
    """Once every band is on the window is not multiplied in (×1 is exact): the same bits
    as multiplying; a window loaded from a state dict is applied whatever it was before."""
    x = torch.rand(9, 3) * 2 - 1
    enc = PositionalEncoding(3, 4, anneal_steps=400)
    enc.set_progress(10_000)
    assert enc._all_on                           # the skip is taken
    xb = x[:, None, :] * enc.freqs[:, None]
    feats = torch.cat([torch.sin(xb), torch.cos(xb)], dim=-1) * enc.window[:, None]
    assert torch.equal(enc(x), torch.cat([x, feats.reshape(9, -1)], dim=-1))
    half = PositionalEncoding(3, 4, anneal_steps=400)
    half.set_progress(150)                       # window (1, 0.5, 0, 0)
    enc.load_state_dict(half.state_dict())
    assert not enc._all_on
    assert torch.equal(enc(x), half(x)) and torch.equal(enc(x)[:, 15:], torch.zeros(9, 12))
    none = PositionalEncoding(3, 4, anneal_steps=0)
    half.load_state_dict(none.state_dict())      # all on, loaded: no longer scaled
    assert half._all_on and torch.equal(half(x), none(x))
    # through the field, as a checkpoint is loaded: each encoding's hook runs
    on, annealing = (NeRFField(depth=1, width=8, pos_bands=3, time_bands=2, anneal_steps=a)
                     for a in (0, 400))
    annealing.set_progress(100)
    on.load_state_dict(annealing.state_dict())
    assert not on.pos_enc._all_on and not on.time_enc._all_on
    xyz, t = torch.rand(9, 3), torch.rand(9, 1)
    assert torch.equal(on.encode(xyz, t), annealing.encode(xyz, t))
    for e in (on.pos_enc, on.time_enc):           # the host copy follows the loaded buffer
        assert e.weights == tuple(e.window.tolist())
    assert on.pos_enc.weights[2] == 0.0 < on.pos_enc.weights[0]


@pytest.mark.parametrize("step", [0, 150, 333, 10_000])
def test_encoding_is_the_written_out_formula_in_the_dtype_asked(step: int) -> None:
    """Only the bands that are on are computed; the result is the band-by-band formula
    with the window applied, and in bf16 the cast of the float32 encoding."""
    enc = PositionalEncoding(3, 5, anneal_steps=1000)
    enc.set_progress(step)
    x = torch.rand(11, 3) * 2 - 1
    w = torch.tensor(band_window(5, step, 1000))
    parts = [x]
    for k in range(5):
        parts += [w[k] * torch.sin(2.0 ** k * x), w[k] * torch.cos(2.0 ** k * x)]
    ref = torch.cat(parts, dim=-1)
    assert torch.allclose(enc(x), ref, atol=1e-7, rtol=0)
    assert enc.bands_on == int((w > 0).sum())
    assert torch.equal(enc(x, torch.bfloat16), enc(x).to(torch.bfloat16))


def test_band_annealing_callback_sets_every_encoding() -> None:
    field = NeRFField(depth=2, width=8, skip=-1, pos_bands=5, time_bands=3, anneal_steps=1000)
    (callback,) = field.callbacks()
    assert isinstance(callback, BandAnnealing)
    module = nn.ModuleDict({"field": field})
    callback.on_train_batch_start(SimpleNamespace(global_step=300), module, None, 0)
    assert field.pos_enc.window.tolist() == pytest.approx(band_window(5, 300, 1000))
    assert field.time_enc.window.tolist() == pytest.approx(band_window(3, 300, 1000))
    # time: alpha = 3 * 300 / 1000 = 0.9 -> band 0 at (1 - cos(0.9 pi)) / 2, the rest off
    assert field.time_enc.window.tolist() == pytest.approx(
        [0.5 * (1 - math.cos(0.9 * math.pi)), 0.0, 0.0])


def test_nerf_field_architecture_and_parameter_count() -> None:
    f = NeRFField()
    in_dim = 3 * 29 + 1 * 15  # raw + sin/cos of 14 (position) and 7 (time) bands
    widths = [layer.in_features for layer in f.layers]
    assert widths == [in_dim, 256, 256, 256, 256, 256 + in_dim, 256, 256]
    expected = ((in_dim + 1) * 256 + 7 * 257 * 256 + in_dim * 256  # trunk incl. skip inputs
                + 257 * 1                                        # density head
                + 257 * 256 + 257 * 128 + 129 * 3)               # colour 256 -> 128 -> 3
    assert sum(p.numel() for p in f.parameters()) == expected
    assert isinstance(f, Field)
    sigma, rgb = f(torch.rand(100, 3) * 2 - 1, torch.rand(100, 1))
    assert sigma.shape == (100,) and rgb.shape == (100, 3)
    assert bool((sigma >= 0).all()) and bool(((rgb > 0) & (rgb < 1)).all())
    groups = f.param_groups(1e-4)
    assert len(groups) == 1 and groups[0]["lr"] == 1e-4
    with pytest.raises(InputError, match="depth"):
        NeRFField(depth=0)


def test_nerf_field_is_the_authors_layers_and_initialisation() -> None:
    """2·ReLU, the skip input first, density head xavier (gain 1) with bias ~ N(0, 1) and no
    shift, colour remap linear, hidden colour layer initialised as with 283 inputs."""
    torch.manual_seed(0)
    biases = torch.stack([NeRFField(depth=2, width=64, skip=-1).density.bias for _ in range(400)])
    assert abs(biases.mean().item()) < 0.15 and abs(biases.std().item() - 1.0) < 0.1
    f = NeRFField(depth=3, width=32, skip=0, pos_bands=2, time_bands=1, remap_width=16,
                  colour_width=8)
    w = f.density.weight
    xavier = math.sqrt(6.0 / (32 + 1))
    assert w.abs().max().item() <= xavier and w.abs().max().item() > 0.5 * xavier
    bound = 1.0 / math.sqrt(16 + 27)
    assert f.colour_hidden.weight.abs().max().item() <= bound
    # the forward pass written out: 2·relu, [encoding, h] after layer `skip`, linear remap
    x, t = torch.rand(7, 3) * 2 - 1, torch.rand(7, 1)
    def lin(layer: nn.Linear, h: torch.Tensor) -> torch.Tensor:
        return h @ layer.weight.T + layer.bias

    enc = f.encode(x, t)
    h0 = 2 * torch.relu(lin(f.layers[0], enc))
    h1 = 2 * torch.relu(lin(f.layers[1], torch.cat([enc, h0], -1)))
    h2 = 2 * torch.relu(lin(f.layers[2], h1))
    sigma = torch.nn.functional.softplus(lin(f.density, h2)).squeeze(-1)
    rgb = torch.sigmoid(lin(f.colour_out,
                            2 * torch.relu(lin(f.colour_hidden, lin(f.colour_remap, h2)))))
    got = f(x, t)
    assert torch.allclose(got[0], sigma, atol=1e-6) and torch.allclose(got[1], rgb, atol=1e-6)


def test_the_layers_are_modules_whose_hooks_run() -> None:
    """Every linear layer is called as a module: a forward hook on each sees the inputs of
    the written-out pass (the encoding, then the hidden activations)."""
    f = NeRFField(depth=3, width=16, skip=0, pos_bands=2, time_bands=1, remap_width=8,
                  colour_width=8)
    seen: dict[str, tuple[int, ...]] = {}
    for name, module in f.named_modules():
        if isinstance(module, nn.Linear):
            module.register_forward_hook(
                lambda m, inp, out, name=name: seen.__setitem__(name, tuple(out.shape)))
    f(torch.rand(5, 3), torch.rand(5, 1))
    assert seen == {"layers.0": (5, 16), "layers.1": (5, 16), "layers.2": (5, 16),
                    "density": (5, 1), "colour_remap": (5, 8), "colour_hidden": (5, 8),
                    "colour_out": (5, 3)}


def test_config_instantiates_the_field_and_carries_the_optimiser() -> None:
    from eventrecon.engine.build import build_field

    cfg = OmegaConf.load(CONF)
    assert open(CONF).readline().startswith("# python train.py model=nerf")
    assert cfg.optim.lr == 1e-4 and cfg.optim.weight_decay == 0.1
    # the model file inside a run config: its schedule is in the paper's steps
    small = OmegaConf.merge(cfg, dict(depth=2, width=16, pos_bands=2, time_bands=1))
    run = OmegaConf.create({"trainer": {"max_steps": 1000, "schedule": "paper",
                                        "paper_steps": 150_000}, "model": small})
    f = build_field(run.model)
    assert isinstance(f, NeRFField) and len(f.layers) == 2
    assert f.pos_enc.anneal_steps == f.time_enc.anneal_steps == 4000  # the paper's value


@pytest.fixture
def one_thread():
    """Tiny matrices: one thread avoids OpenMP oversubscription on a shared machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_nerf_field_fits_a_tiny_target(one_thread) -> None:
    gen = torch.Generator().manual_seed(0)
    f = NeRFField(depth=3, width=64, skip=1, pos_bands=4, time_bands=2, anneal_steps=0,
                  colour_width=32)
    xyz = torch.rand(32, 3, generator=gen) * 2 - 1
    t = torch.rand(32, 1, generator=gen)
    target_sigma = 5 * torch.rand(32, generator=gen)
    target_rgb = 0.1 + 0.8 * torch.rand(32, 3, generator=gen)
    opt = torch.optim.Adam(f.parameters(), lr=3e-3)
    for _ in range(400):
        sigma, rgb = f(xyz, t)
        loss = ((sigma - target_sigma) ** 2).mean() + ((rgb - target_rgb) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        sigma, rgb = f(xyz, t)
    assert float((sigma - target_sigma).abs().max()) < 0.1
    assert float((rgb - target_rgb).abs().max()) < 0.02


def test_render_through_nerf_field_under_bf16_autocast_is_finite() -> None:
    f = NeRFField(depth=4, width=32, skip=1, pos_bands=14, time_bands=7, anneal_steps=0,
                  colour_width=16)
    o = torch.tensor([[-2.0, -0.25, 0.0], [0.0, -2.0, 0.1], [1.0, -0.25, -2.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    t = torch.tensor([[0.0], [1.0], [0.5]])
    with torch.autocast("cpu", dtype=torch.bfloat16):
        levels = VolumeRenderer(16, 16).render_rays(f, o, d, t, torch.full((3, 3), 0.5),
                                                    perturb=True,
                                                    gen=torch.Generator().manual_seed(0))
        loss = sum(((lv["rgb"] - 0.3) ** 2).mean() + lv["opacity"].mean() for lv in levels)
    loss.backward()
    assert all(lv["rgb"].dtype == torch.float32 for lv in levels)
    assert bool(torch.isfinite(loss))
    grads = torch.cat([p.grad.reshape(-1) for p in f.parameters()])
    assert bool(torch.isfinite(grads).all()) and float(grads.abs().sum()) > 0


def test_band_annealing_follows_the_global_step_in_a_lightning_fit(tmp_path, one_thread) -> None:
    import lightning.pytorch as pl

    class Tiny(pl.LightningModule):
        def __init__(self) -> None:
            super().__init__()
            self.field = NeRFField(depth=1, width=8, skip=-1, pos_bands=4, time_bands=2,
                                   anneal_steps=8, colour_width=4)
            self.seen: list[list[float]] = []

        def training_step(self, batch, batch_idx):
            self.seen.append(self.field.pos_enc.window.tolist())
            sigma, rgb = self.field(batch[0], batch[1])
            return sigma.mean() + rgb.mean()

        def configure_optimizers(self):
            return torch.optim.AdamW(self.field.param_groups(1e-3), weight_decay=0.1)

    data = torch.utils.data.TensorDataset(torch.rand(16, 3), torch.rand(16, 1))
    module = Tiny()
    trainer = pl.Trainer(max_steps=5, logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False,
                         callbacks=module.field.callbacks(), default_root_dir=tmp_path,
                         accelerator="cpu")
    trainer.fit(module, torch.utils.data.DataLoader(data, batch_size=4))
    assert len(module.seen) == 5
    for step, window in enumerate(module.seen):
        assert window == pytest.approx(band_window(4, step, 8), abs=1e-7)


@pytest.mark.parametrize("autocast", [False, True])
@pytest.mark.parametrize("skip", [-1, 1])
def test_density_alone_is_the_forward_density_bit_for_bit(skip, autocast) -> None:
    """``density_only`` (what the occupancy grid asks) gives ``forward``'s density to the
    bit, with and without the skip, in fp32 and bf16, with the colour branch removed."""
    torch.manual_seed(4)
    f = NeRFField(depth=3, width=32, skip=skip, pos_bands=6, time_bands=3, remap_width=32,
                  colour_width=16, anneal_steps=0)
    xyz, t = torch.rand(513, 3) * 2 - 1, torch.rand(513, 1)
    with torch.no_grad(), torch.autocast("cpu", torch.bfloat16, enabled=autocast):
        full = f(xyz, t)[0]
        f.colour_remap = f.colour_hidden = f.colour_out = None   # the colour is never asked
        alone = f.density_only(xyz, t)
    assert alone.dtype == full.dtype == (torch.bfloat16 if autocast else torch.float32)
    assert torch.equal(alone, full) and float(alone.float().std()) > 0
