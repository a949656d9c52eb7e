"""Frame-side sensor effects (RGB frames of the training views), registered by name.

Each effect maps a float64 linear image ``[H, W, 3]`` (``[H, W]`` after ``bayer_raw``)
to the next, in the order the scene lists them; the result is gamma-encoded to PNG.

=================================== =====================================================
name (parameters)                   what it does
=================================== =====================================================
exposure_blur (exposure_s, samples) replaces the sharp render by its time average over
                                    ``[t − e/2, t + e/2] ∩ [0, 1]`` (midpoint rule,
                                    ``samples`` renders, default enough for one sample per
                                    ``max_step``, at least 8); must be listed first
vignetting (strength)               ``I ← I·(1 − strength·ρ²)``, ``ρ`` distance to the
                                    principal point over its largest value (the corner)
low_light (photons, read_noise)     ``I ← Poisson(photons·I)/photons + N(0, read_noise²)``
crf (eps, gain)                     the rig's linear CRF with offset,
                                    ``clip(gain·I − eps, 0, 1)``
                                    (:func:`eventrecon.capture.crf_model.apply_crf`)
quantize_8bit                       ``round(255·clip(I, 0, 1))/255`` (linear 8-bit ADC;
                                    the PNG's gamma encoding then rounds again)
bayer_raw                           single-channel RGGB mosaic ``[H, W]``
=================================== =====================================================
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from eventrecon.capture.crf_model import apply_crf
from eventrecon.sim.event_effects import bayer_channel
from eventrecon.sim.registry import Effect, Param, Registry, non_negative, positive

__all__ = ["FRAME_EFFECTS", "FrameContext"]

FRAME_EFFECTS = Registry("frames")


@dataclass
class FrameContext:
    """What a frame effect may use: the view's sharp renderer and geometry.

    Attributes:
        render: ``render(t [T]) -> [T, H, W, 3]`` sharp linear images at normalised times.
        t: normalised frame time; duration_s: scene duration in seconds.
        K: ``[3, 3]`` intrinsics of the view; max_step: the event core's largest step.
    """

    render: Callable[[np.ndarray], np.ndarray]
    t: float
    duration_s: float
    K: np.ndarray
    max_step: float = 2e-3


@FRAME_EFFECTS.register
class ExposureBlur(Effect):
    name = "exposure_blur"
    first_only = True
    PARAMS = {"exposure_s": Param(float, check=positive, expect="an exposure > 0 s"),
              "samples": Param(int, 0, non_negative, "a sample count ≥ 0 (0 = automatic)")}

    def sample_times(self, t: float, duration_s: float, max_step: float) -> np.ndarray:
        """Midpoint-rule times of the exposure window around ``t`` (normalised)."""
        half = 0.5 * self.p["exposure_s"] / duration_s
        t0, t1 = max(0.0, t - half), min(1.0, t + half)
        n = self.p["samples"] or max(8, math.ceil((t1 - t0) / max_step))
        return t0 + (np.arange(n) + 0.5) * (t1 - t0) / n

    def apply(self, img: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        times = self.sample_times(ctx.t, ctx.duration_s, ctx.max_step)
        return ctx.render(times).mean(0)


@FRAME_EFFECTS.register
class Vignetting(Effect):
    name = "vignetting"
    PARAMS = {"strength": Param(float, check=lambda v: 0 <= v < 1, expect="a value in [0, 1)")}

    def apply(self, img: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        H, W = img.shape[:2]
        cx, cy = ctx.K[0, 2], ctx.K[1, 2]
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        r2 = (u - cx) ** 2 + (v - cy) ** 2
        corners = [(x - cx) ** 2 + (y - cy) ** 2 for x in (0, W - 1) for y in (0, H - 1)]
        fall = 1.0 - self.p["strength"] * r2 / max(corners)
        return img * (fall if img.ndim == 2 else fall[..., None])


@FRAME_EFFECTS.register
class LowLight(Effect):
    name = "low_light"
    PARAMS = {"photons": Param(float, check=positive, expect="photons at full scale > 0"),
              "read_noise": Param(float, 0.0, non_negative, "a std ≥ 0")}

    def apply(self, img: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        n = self.p["photons"]
        shot = rng.poisson(np.clip(img, 0, None) * n) / n
        return shot + self.p["read_noise"] * rng.standard_normal(img.shape)


@FRAME_EFFECTS.register
class Crf(Effect):
    name = "crf"
    PARAMS = {"eps": Param(float, check=non_negative, expect="an offset ≥ 0"),
              "gain": Param(float, 1.0, positive, "a gain > 0")}

    def apply(self, img: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        return apply_crf(img, self.p["eps"], self.p["gain"])


@FRAME_EFFECTS.register
class Quantize8bit(Effect):
    name = "quantize_8bit"

    def apply(self, img: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        """A linear 8-bit ADC, as the DAVIS APS readout (value ∝ light through the CRF).

        The dataset stores frames gamma-encoded (``PNG = round(255·I^(1/2.2))``, the
        method's convention), which rounds a second time: in the shadows the encoded
        levels are finer than the ADC's, so the ADC steps survive; above ``I ≈ 0.99``
        neighbouring ADC levels (e.g. 254/255 and 1) fall on the same PNG value.
        """
        return np.round(255.0 * np.clip(img, 0.0, 1.0)) / 255.0


@FRAME_EFFECTS.register
class BayerRaw(Effect):
    name = "bayer_raw"

    def apply(self, img: np.ndarray, ctx: FrameContext, rng: np.random.Generator) -> np.ndarray:
        if img.ndim == 2:
            return img
        H, W = img.shape[:2]
        rows, cols = np.mgrid[0:H, 0:W]
        return np.take_along_axis(img, bayer_channel(rows, cols)[..., None], axis=2)[..., 0]
