"""Held-out evaluation: render the validation views at every ground-truth time and score them.

:func:`render_heldout` renders every held-out view at every ground-truth time
(cross-fading segments inside their overlaps); :func:`evaluate_heldout` scores the renders
(PSNR, SSIM, LPIPS on the sRGB-encoded images, as the published PNGs are compared;
optionally the colour-corrected variant); :func:`write_renders` writes
``renders/<view>/<frame:04d>.png`` and an animated GIF per view (render | ground truth).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from eventrecon.common.colour import linear_to_srgb
from eventrecon.common.progress import TaskProgress
from eventrecon.data.batcher import Segment, background_linear
from eventrecon.data.segments import crossfade_weights
from eventrecon.data.types import SplitData
from eventrecon.evaluation.metrics import evaluate_images, psnr, subject_scores
from eventrecon.fields.base import Field
from eventrecon.render.renderer import Renderer

__all__ = ["render_heldout", "encode", "score_images", "cheap_psnr", "evaluate_heldout",
           "write_renders", "render_and_score"]

log = logging.getLogger(__name__)


@torch.no_grad()
def render_heldout(models: Sequence[tuple[Field, Renderer]], segments: Sequence[Segment],
                   split: SplitData, views: Sequence[int], frame_idx: Sequence[int],
                   chunk: int = 8192) -> np.ndarray:
    """Linear renders ``[len(frame_idx), len(views), H, W, 3]`` of held-out views.

    ``models[k]`` is segment ``k``'s field and renderer (each segment keeps its own
    clipping state). At time ``t`` the segments containing ``t`` are blended by
    :func:`~eventrecon.data.segments.crossfade_weights` (linear-space ramp).
    """
    bg = background_linear(split)
    device = next(iter(models[0][0].parameters())).device
    H, W = split.cameras.height, split.cameras.width
    out = np.zeros((len(frame_idx), len(views), H, W, 3), np.float32)
    progress = TaskProgress("held-out renders", len(frame_idx) * len(views))
    for a, f in enumerate(frame_idx):
        t = float(split.frame_times[f])
        for b, v in enumerate(views):
            img = torch.zeros(H, W, 3, device=device)
            for seg_i, w in crossfade_weights(segments, t):
                seg = segments[seg_i]
                t_norm = min(1.0, max(0.0, float(seg.normalise(t))))
                field, renderer = models[seg_i]
                res = renderer.render_image(field, split.cameras, v, t_norm,
                                            bg[v].to(device), chunk=chunk)
                img += w * res["rgb"].to(device)  # segments may live on different devices
            out[a, b] = img.clamp(0, 1).cpu().numpy()
            progress.step()
    return out


def encode(linear: np.ndarray) -> np.ndarray:
    """Linear radiance → the 8-bit encoding of the saved renders, as float32 in [0, 1]
    (what is scored: the published ground truth is compared as stored)."""
    return linear_to_srgb(linear).astype(np.float32) / 255.0


def score_images(preds_lin: Sequence[np.ndarray], gts_u8: Sequence[np.ndarray],
                 lpips: bool | tuple[str, ...] = True,
                 color_correct: bool | str = "none") -> dict:
    """PSNR / SSIM / LPIPS of linear renders ``[H, W, 3]`` against stored frames
    (:func:`eventrecon.evaluation.metrics.evaluate_images` on the encoded images)."""
    return evaluate_images([encode(p) for p in preds_lin],
                           [g.astype(np.float32) / 255.0 for g in gts_u8],
                           lpips=lpips, color_correct=color_correct)


def cheap_psnr(preds_lin: Sequence[np.ndarray], gts_u8: Sequence[np.ndarray]) -> float:
    """``−10 log10`` of the mean squared error over every given pixel (any shapes, each
    render against its stored ground truth): the cheap point of the training curve."""
    mse = float(np.mean([np.mean((encode(p) - g.astype(np.float32) / 255.0) ** 2)
                         for p, g in zip(preds_lin, gts_u8)]))
    return -10.0 * math.log10(max(mse, 1e-12))


def evaluate_heldout(renders_lin: np.ndarray, split: SplitData, views: Sequence[int],
                     frame_idx: Sequence[int], lpips: bool = True,
                     color_correct: bool | str = "none") -> dict:
    """PSNR / SSIM / LPIPS of the renders ``[F, V, H, W, 3]`` against the ground-truth PNGs.

    Also ``psnr_background``: the PSNR of the background alone (what a field with zero
    density everywhere renders) on the same frames, and ``gain_psnr`` over it: a run
    close to it has learnt little of the scene; a low-contrast scene can score high with
    nothing in it. When the split has masks (the simulator's; ``mask/`` of a published
    scene): ``psnr_subject``, ``ssim_subject`` on the subject's pixels, the empty field's
    ``psnr_background_subject`` and ``gain_psnr_subject``.
    """
    bg = encode(background_linear(split).clamp(0, 1).numpy())
    preds, gts, empty = [], [], []
    for a, f in enumerate(frame_idx):
        for b, v in enumerate(views):
            preds.append(renders_lin[a, b])
            gts.append(split.frames[f, v])
            empty.append(bg[v])
    result = score_images(preds, gts, lpips=lpips, color_correct=color_correct)
    gt_enc = np.stack(gts).astype(np.float32) / 255.0
    result["psnr_background"] = psnr(np.stack(empty), gt_enc)
    result["gain_psnr"] = result["psnr"] - result["psnr_background"]
    if split.masks is not None:  # the subject's region at each evaluated time
        masks = np.stack([split.masks[f, v] for f in frame_idx for v in views])
        subject = subject_scores(np.stack([encode(p) for p in preds]), gt_enc, masks)
        empty_subject = subject_scores(np.stack(empty), gt_enc, masks)
        if subject:
            result.update(subject)
            result["psnr_background_subject"] = empty_subject["psnr_subject"]
            result["gain_psnr_subject"] = (subject["psnr_subject"]
                                           - empty_subject["psnr_subject"])
    return result


def write_renders(renders_lin: np.ndarray, split: SplitData, views: Sequence[int],
                  frame_idx: Sequence[int], out_dir: Path) -> list[Path]:
    """PNG per frame and an animated GIF per view (render | ground truth side by side)."""
    import imageio.v3 as iio

    written = []
    for b, v in enumerate(views):
        name = split.cameras.names[v]
        vdir = out_dir / "renders" / name
        vdir.mkdir(parents=True, exist_ok=True)
        frames = []
        for a, f in enumerate(frame_idx):
            img = linear_to_srgb(renders_lin[a, b])
            iio.imwrite(vdir / f"{int(round(split.frame_times[f])):04d}.png", img)
            frames.append(np.concatenate([img, split.frames[f, v]], axis=1))
        gif = out_dir / "renders" / f"{name}.gif"
        iio.imwrite(gif, np.stack(frames), duration=80, loop=0)
        written.append(gif)
    return written


def render_and_score(models: list[tuple[Field, Renderer]], segments: list[Segment],
                     heldout: SplitData, views: list[int], frames: list[int], out_dir: Path,
                     chunk: int, color_correct: bool | str = "none") -> dict[str, Any]:
    """Render the held-out ``views`` at ``frames`` (cross-fading segments), write the PNGs
    and GIFs below ``out_dir`` and return PSNR / SSIM / LPIPS (and ``psnr_background``)."""
    renders = render_heldout(models, segments, heldout, views, frames, chunk=chunk)
    write_renders(renders, heldout, views, frames, out_dir)
    return evaluate_heldout(renders, heldout, views, frames, color_correct=color_correct)
