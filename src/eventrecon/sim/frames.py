"""RGB frames of the training views, background frames and held-out ground truth.

- Training frames at ``rgb_fps`` (times from :func:`eventrecon.sim.spec.frame_times`):
  sharp linear render → the scene's frame effects in order → sRGB-encoded uint8
  (``round(255·clip(I)^(1/2.2))``).
- Background of every view: the empty scene (every moving object removed; static ones,
  e.g. a ground plane, kept) through the same frame effects (training views: what the
  camera records of the empty set) or sharp (held-out views, for evaluation).
- Ground truth: sharp renders of the held-out views at ``eval_fps`` times.
- Subject masks of both splits at their frame times (:func:`render_masks`): the pixels
  whose ray first hits a subject (an object the background leaves out). Always sharp:
  an exposure-blurred frame gets the mask at its own time.

Random effects draw from ``effect_rng(seed, "frames", name, occurrence, kind, view, k)``
(``kind`` 0 = frame ``k``, 1 = background).
"""

from __future__ import annotations

import numpy as np
import torch

from eventrecon import TIME_SPAN
from eventrecon.common.progress import TaskProgress
from eventrecon.data.types import linear_to_srgb, srgb_to_linear
from eventrecon.sim.config import effect_rng
from eventrecon.sim.frame_effects import FrameContext
from eventrecon.sim.raytrace import PixelRenderer
from eventrecon.sim.scene import Scene
from eventrecon.sim.spec import SceneSpec

__all__ = ["render_frames", "render_backgrounds", "render_masks", "empty_scene",
           "apply_frame_effects"]


def empty_scene(scene: Scene) -> Scene:
    """The empty stage: the scene without its moving objects and its static subjects."""
    return Scene([o for o in scene.objects if o.in_background], scene.light, scene.background)


def _render_fn(prend: PixelRenderer, view: int):
    def render(times: np.ndarray) -> np.ndarray:
        return prend.images(view, torch.as_tensor(np.atleast_1d(times), dtype=torch.float64)
                            ).numpy()
    return render


def apply_frame_effects(spec: SceneSpec, img: np.ndarray, ctx: FrameContext,
                        ids: tuple[int, ...]) -> np.ndarray:
    """Run the spec's frame effects on a linear image ``[H, W, 3]`` (float64)."""
    for e in spec.frame_effects:
        img = e.apply(img, ctx, effect_rng(spec.seed, "frames", e.name, e.occurrence, *ids))
    return img


def render_frames(spec: SceneSpec, prend: PixelRenderer, times: np.ndarray,
                  effects: bool = True) -> np.ndarray:
    """Frames of every view of ``prend`` at time units ``times [F]``.

    Returns:
        ``[F, V, H, W, 3]`` uint8 (``[F, V, H, W]`` after ``bayer_raw``), sRGB-encoded.
    """
    out = []
    progress = TaskProgress(f"rendering {'frames' if effects else 'ground truth'}",
                            len(times) * len(prend.cams))
    for k, tu in enumerate(times):
        row = []
        for v in range(len(prend.cams)):
            t = float(tu) / TIME_SPAN
            img = prend.image(v, t).numpy()
            if effects:
                ctx = FrameContext(_render_fn(prend, v), t, spec.duration_s,
                                   prend.cams.K[v].numpy(), spec.max_step)
                img = apply_frame_effects(spec, img, ctx, (0, v, k))
            row.append(linear_to_srgb(img))
            progress.step()
        out.append(np.stack(row))
    return np.stack(out)


def render_backgrounds(spec: SceneSpec, prend: PixelRenderer, effects: bool = True
                       ) -> np.ndarray:
    """``[V, H, W, 3]`` uint8 empty-scene plate per view (``[V, H, W]`` for Bayer raw).

    With ``effects``, the plate is captured as a practitioner would: ``N =
    spec.background_exposures`` frames of the empty scene, each through the frame effects
    with its own noise draw and 8-bit encoding, linearised, averaged and encoded again,

    .. math:: B = q\\big(\\tfrac1N \\textstyle\\sum_{k<N} q^{-1}(q(f_k(I)))\\big),

    ``q`` the 8-bit gamma encoding, ``f_k`` the effect chain with noise draw ``k``
    (averaging the linear values keeps the plate's mean that of the frames; averaging
    the encoded values would darken a noisy dark plate). Deterministic
    effects (vignetting, the CRF offset, blur of a still scene) survive unchanged; a noise
    effect's spread shrinks by ``√N``. Without effects, the clean sRGB empty scene.
    """
    empty = PixelRenderer(empty_scene(spec.scene), prend.cams, spec.frame_supersample)
    n_exp = spec.background_exposures if spec.frame_effects else 1
    out = []
    for v in range(len(prend.cams)):
        img = empty.image(v, 0.0).numpy()
        if not effects:
            out.append(linear_to_srgb(img))
            continue

        def still(times: np.ndarray, img=img) -> np.ndarray:
            return np.broadcast_to(img, (len(np.atleast_1d(times)),) + img.shape)
        ctx = FrameContext(still, 0.0, spec.duration_s, prend.cams.K[v].numpy(),
                           spec.max_step)
        total = sum(srgb_to_linear(linear_to_srgb(apply_frame_effects(spec, img, ctx,
                                                                      (1, v, k))))
                    for k in range(n_exp))
        out.append(linear_to_srgb(total / n_exp))
    return np.stack(out)


def render_masks(prend: PixelRenderer, times: np.ndarray) -> np.ndarray:
    """``[F, V, H, W]`` bool subject masks of every view at time units ``times [F]``
    (:meth:`PixelRenderer.masks`, sharp at each frame's time)."""
    t = torch.as_tensor(np.asarray(times, dtype=np.float64) / TIME_SPAN)
    if t.numel() == 0:
        return np.zeros((0, len(prend.cams), prend.cams.height, prend.cams.width), bool)
    return np.stack([prend.masks(v, t).numpy() for v in range(len(prend.cams))], axis=1)
