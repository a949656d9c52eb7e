"""One test per frame-side effect (and the frame pipeline), with numbers."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from eventrecon.common.errors import InputError
from eventrecon.data.types import srgb_to_linear
from eventrecon.sim.config import effect_rng
from eventrecon.sim.frame_effects import FRAME_EFFECTS, FrameContext
from eventrecon.sim.frames import render_backgrounds, render_frames
from eventrecon.sim.raytrace import PixelRenderer
from eventrecon.sim.spec import build_cameras, parse_spec

K = np.array([[30.0, 0, 19.5], [0, 30.0, 14.5], [0, 0, 1]])


def build(*items):
    return FRAME_EFFECTS.build(list(items), "test")


def ctx(render=None, t=0.5):
    return FrameContext(render or (lambda ts: None), t, 2.0, K, 2e-3)


def rng():
    return effect_rng(5, "frames", "test", 0, 0)


def _scene():
    cfg = {"name": "f", "width": 24, "height": 18, "seed": 1,
           "rig": {"n_train": 1, "n_heldout": 0},
           "objects": [{"type": "sphere", "radius": 0.2, "position": [0, -0.3, 0],
                        "texture": {"type": "checker", "colors": [[1, 0.2, 0.1], [0.1, 0.2, 1]],
                                    "size": 0.08},
                        "motion": [{"type": "orbit", "radius": 0.2}, {"type": "spin"}]}]}
    spec = parse_spec(cfg)
    cams, _ = build_cameras(spec)
    return spec, PixelRenderer(spec.scene, cams)


def test_exposure_blur_equals_time_average_of_sharp_renders():
    spec, pr = _scene()
    (fx,) = build({"name": "exposure_blur", "exposure_s": 0.2, "samples": 40})
    render = lambda ts: pr.images(0, torch.as_tensor(np.asarray(ts, float))).numpy()  # noqa: E731
    blurred = fx.apply(None, FrameContext(render, 0.5, 2.0, K, 2e-3), rng())
    # independent reference: 400-sample average over [0.45, 0.55] (0.2 s of 2 s)
    ref = render(np.linspace(0.45, 0.55, 400)).mean(0)
    sharp = render([0.5])[0]
    assert np.abs(blurred - ref).mean() < 0.003
    assert np.abs(sharp - ref).mean() > 10 * np.abs(blurred - ref).mean()
    # clipped at the sequence start; automatic count is one sample per max_step
    t = build({"name": "exposure_blur", "exposure_s": 0.2})[0].sample_times(0.0, 2.0, 2e-3)
    assert t.min() > 0 and t.max() < 0.05 and t.size == 25


def test_crf_offset_recovered_from_frame_values():
    (fx,) = build({"name": "crf", "eps": 0.03})
    irr = np.linspace(0.0, 1.2, 200)
    v = fx.apply(irr, ctx(), rng())
    lin = (v > 0) & (v < 1)
    slope, intercept = np.polyfit(irr[lin], v[lin], 1)
    assert slope == pytest.approx(1.0, abs=1e-12) and -intercept == pytest.approx(0.03, abs=1e-12)
    assert v.min() == 0.0 and v.max() == 1.0


def test_low_light_noise_variance():
    (fx,) = build({"name": "low_light", "photons": 400.0, "read_noise": 0.02})
    img = np.full((200, 200, 3), 0.25)
    out = fx.apply(img, ctx(), rng())
    assert out.mean() == pytest.approx(0.25, abs=0.002)
    assert out.var() == pytest.approx(0.25 / 400 + 0.02 ** 2, rel=0.03)


def test_vignetting_falloff():
    (fx,) = build({"name": "vignetting", "strength": 0.4})
    out = fx.apply(np.ones((30, 40, 3)), ctx(), rng())
    assert out[0, 0, 0] == pytest.approx(0.6) and out[29, 39, 1] == pytest.approx(0.6)
    assert out.max() <= 1.0 and out[14, 19, 0] > 0.999


def test_quantize_8bit_levels():
    (fx,) = build({"name": "quantize_8bit"})
    x = np.random.default_rng(0).uniform(-0.1, 1.1, 10000)
    q = fx.apply(x, ctx(), rng())
    np.testing.assert_allclose(q * 255, np.round(q * 255), atol=1e-9)
    inside = (x >= 0) & (x <= 1)
    assert np.abs(q - x)[inside].max() <= 0.5 / 255 + 1e-12
    assert len(np.unique(q)) <= 256


def test_bayer_raw_channel():
    (fx,) = build({"name": "bayer_raw"})
    img = np.zeros((4, 6, 3))
    img[..., 0], img[..., 1], img[..., 2] = 0.1, 0.5, 0.9
    raw = fx.apply(img, ctx(), rng())
    assert raw.shape == (4, 6)
    assert raw[0, 0] == 0.1 and raw[0, 1] == 0.5 and raw[1, 0] == 0.5 and raw[1, 1] == 0.9


def test_frame_pipeline_gamma_and_order():
    spec, pr = _scene()
    frames = render_frames(spec, pr, np.array([0.0, 500.0]), effects=False)
    assert frames.shape == (2, 1, 18, 24, 3) and frames.dtype == np.uint8
    lin = pr.image(0, 0.5).numpy()
    np.testing.assert_allclose(srgb_to_linear(frames[1, 0]), lin, atol=0.02)
    bg = render_backgrounds(spec, pr, effects=False)
    assert np.all(bg == np.round(255 * 0.353 ** (1 / 2.2)))
    with pytest.raises(InputError, match=r"frames\[1\].name: expected exposure_blur as the first"):
        build({"name": "crf", "eps": 0.03}, {"name": "exposure_blur", "exposure_s": 0.1})
    with pytest.raises(InputError, match=r"frames\[0\].photons"):
        build({"name": "low_light", "photons": 0.0})


def _plate(frames: list, exposures: int) -> np.ndarray:
    """Linear ``[H, W, 3]`` training-split plate of a 24×18 empty-ish scene."""
    cfg = {"name": "p", "width": 24, "height": 18, "seed": 2,
           "rig": {"n_train": 1, "n_heldout": 0}, "background": [0.05, 0.05, 0.05],
           "objects": [], "frames": frames, "background_exposures": exposures}
    spec = parse_spec(cfg)
    cams, _ = build_cameras(spec)
    return srgb_to_linear(render_backgrounds(spec, PixelRenderer(spec.scene, cams))[0])


def test_background_plate_averages_the_noise_of_its_exposures():
    """The plate is the mean of N exposures: the noise about the noise-free chain shrinks
    by √N (√16 = 4) and its mean stays that of a frame (no darkening by the gamma)."""
    clean = _plate([{"name": "vignetting", "strength": 0.3}, {"name": "quantize_8bit"}], 1)
    noisy = [{"name": "vignetting", "strength": 0.3},
             {"name": "low_light", "photons": 300.0, "read_noise": 0.01},
             {"name": "quantize_8bit"}]
    one, sixteen = _plate(noisy, 1), _plate(noisy, 16)
    rms = lambda x: float(np.sqrt(np.mean((x - clean) ** 2)))  # noqa: E731
    assert rms(one) > 0.008                       # a single dark frame is noisy
    assert 0.18 < rms(sixteen) / rms(one) < 0.35  # ≈ 1/4
    # linear averaging keeps the mean (measured −0.3 %); averaging the 8-bit codes would
    # darken this dark plate by 4.0 %
    assert abs(sixteen.mean() - clean.mean()) < 0.02 * clean.mean()
    # a scene without frame noise gets the same plate whatever N is
    det = [{"name": "vignetting", "strength": 0.3}, {"name": "quantize_8bit"}]
    np.testing.assert_array_equal(_plate(det, 1), _plate(det, 32))
    with pytest.raises(InputError, match="background_exposures"):
        _plate(det, 0)
