"""Held-out evaluation: render the validation views at every ground-truth time.

``python -m eventrecon.evaluate run=DIR [ckpt=last|best] [color_correct=true]`` loads a
finished or interrupted run (its ``.hydra/config.yaml`` and per-segment checkpoints),
renders every held-out view at every ground-truth time (cross-fading segments inside
their overlaps), writes ``renders/<view>/<frame:04d>.png`` and an animated GIF per view
(render | ground truth), and saves ``metrics_eval.json`` (PSNR, SSIM, LPIPS on the
sRGB-encoded images, as the published PNGs are compared; ``color_correct=true`` adds the
colour-corrected variant and writes ``metrics_eval_cc.json``).
"""

from __future__ import annotations

import json
import logging
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from eventrecon.build import load_dataset, load_segment, scene_properties
from eventrecon.checkpointing import atomic_write_json
from eventrecon.colour import linear_to_srgb
from eventrecon.data.batcher import Segment, background_linear
from eventrecon.data.properties import SceneProperties
from eventrecon.data.selection import heldout_split, window_frames
from eventrecon.data.types import SplitData
from eventrecon.errors import InputError
from eventrecon.fields.base import Field
from eventrecon.metrics import evaluate_images, psnr, subject_scores
from eventrecon.precision import image_dtype, run_precision
from eventrecon.records import METRICS_FILE, read_metrics, run_info
from eventrecon.render.renderer import Renderer
from eventrecon.segments import crossfade_weights, run_segments, run_window
from eventrecon.taskprogress import TaskProgress

__all__ = ["render_heldout", "encode", "score_images", "cheap_psnr", "evaluate_heldout",
           "write_renders", "render_and_score", "evaluate_models", "evaluate_run",
           "run_config", "run_device", "main"]

log = logging.getLogger(__name__)


@torch.no_grad()
def render_heldout(models: Sequence[tuple[Field, Renderer]], segments: Sequence[Segment],
                   split: SplitData, views: Sequence[int], frame_idx: Sequence[int],
                   chunk: int = 8192) -> np.ndarray:
    """Linear renders ``[len(frame_idx), len(views), H, W, 3]`` of held-out views.

    ``models[k]`` is segment ``k``'s field and renderer (each segment keeps its own
    clipping state). At time ``t`` the segments containing ``t`` are blended by
    :func:`~eventrecon.segments.crossfade_weights` (linear-space ramp).
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
                 lpips: bool = True, color_correct: bool = False) -> dict:
    """PSNR / SSIM / LPIPS of linear renders ``[H, W, 3]`` against stored frames
    (:func:`eventrecon.metrics.evaluate_images` on the encoded images)."""
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
                     color_correct: bool = False) -> dict:
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
                     chunk: int, color_correct: bool = False) -> dict[str, Any]:
    """Render the held-out ``views`` at ``frames`` (cross-fading segments), write the PNGs
    and GIFs below ``out_dir`` and return PSNR / SSIM / LPIPS (and ``psnr_background``)."""
    renders = render_heldout(models, segments, heldout, views, frames, chunk=chunk)
    write_renders(renders, heldout, views, frames, out_dir)
    return evaluate_heldout(renders, heldout, views, frames, color_correct=color_correct)


def run_device(cfg: DictConfig) -> torch.device:
    """Where the run trains and evaluates: its GPU when the trainer asks for one."""
    gpu = str(cfg.trainer.lightning.accelerator) in ("gpu", "cuda", "auto")
    return torch.device("cuda" if gpu and torch.cuda.is_available() else "cpu")


def evaluate_models(cfg: DictConfig, props: SceneProperties, heldout: SplitData,
                    segments: list[Segment], trained: dict[int, tuple[Field, Renderer]],
                    out_dir: Path, device: torch.device,
                    window: tuple[float, float] | None = None) -> dict[str, Any]:
    """Score a run's held-out views on ``device`` as configured (``data.eval_views``,
    ``data.eval_every_frames``; only the frames inside ``window`` when given); segments
    not in ``trained`` are loaded from their ``last.ckpt``."""
    models = []
    for k in range(len(segments)):
        field, renderer = (trained[k] if k in trained
                           else load_segment(cfg, props, out_dir / f"seg{k}"))
        models.append((field.to(device).eval(), renderer))
    views = (list(range(heldout.n_views)) if cfg.data.eval_views is None
             else list(cfg.data.eval_views))
    frames = window_frames(heldout, window, int(cfg.data.eval_every_frames))
    return render_and_score(models, segments, heldout, views, frames, out_dir,
                            cfg.render.chunk)


def _trained_precision(run_dir: Path, cfg: DictConfig) -> str | int:
    """The precision the run trained with: its record's, else the config's resolved here
    (an interrupted run has no record yet). Images render under it, not under what
    ``auto`` would pick on the machine that evaluates."""
    path = run_dir / METRICS_FILE
    try:
        return (read_metrics(path).get("precision") if path.exists() else None) or \
            run_precision(cfg)
    except InputError:
        return run_precision(cfg)


def run_config(run_dir: str | Path) -> DictConfig:
    """A run folder's saved config (``run_dir/.hydra/config.yaml``), or one
    :class:`InputError` naming the file when the folder holds none."""
    cfg_path = Path(run_dir) / ".hydra" / "config.yaml"
    if not cfg_path.is_file():
        raise InputError(cfg_path, "<file>", "the run's saved Hydra config")
    return OmegaConf.load(cfg_path)


def evaluate_run(run_dir: Path, ckpt: str = "last", color_correct: bool = False) -> dict:
    """Re-evaluate a finished or interrupted run from its saved config and checkpoints.

    Every held-out view at every ground-truth time (the paper's protocol; the run's own
    ``metrics.json`` may have used a subset, ``data.eval_every_frames``).
    ``ckpt="last"`` (default) scores the final weights; ``"best"`` the checkpoint that
    scored best on the held-out views during training (a choice made on the test data
    itself, so not an unbiased score). Renders go to ``eval_<ckpt>/renders/``; the
    metrics to ``metrics_eval.json`` (``metrics_eval_cc.json`` with colour correction)
    beside the run's ``metrics.json``.
    """
    run_dir = Path(run_dir)
    cfg = run_config(run_dir)
    ds = load_dataset(cfg)
    props = scene_properties(cfg, ds)
    heldout = heldout_split(ds)
    if heldout is None:
        raise InputError(ds.root, "validation/ or groundtruth/", "a held-out split to evaluate")
    window = run_window(cfg)
    segments = run_segments(cfg, props.segments)
    device = run_device(cfg)
    trained = _trained_precision(run_dir, cfg)
    models = [(field.to(device), renderer) for field, renderer in
              (load_segment(cfg, props, run_dir / f"seg{k}", ckpt, trained)
               for k in range(len(segments)))]
    views = list(range(heldout.n_views))
    frames = window_frames(heldout, window)
    metrics = {**run_info(cfg, ds.meta, data_id=Path(ds.root).name), "checkpoint": ckpt,
               "precision": str(trained),
               "image_autocast": image_dtype(cfg.render, trained, device.type) is not None,
               **render_and_score(models, segments, heldout, views, frames,
                                  run_dir / f"eval_{ckpt}", cfg.render.chunk, color_correct)}
    name = "metrics_eval.json" if not color_correct else "metrics_eval_cc.json"
    atomic_write_json(run_dir / name, metrics)
    return metrics


USAGE = "usage: python -m eventrecon.evaluate run=DIR [ckpt=last|best] [color_correct=true]"


def main(argv: Sequence[str] | None = None) -> int:
    """CLI (see module docstring). Exit 0 done, 2 bad input (one line)."""
    argv = list(argv if argv is not None else sys.argv[1:])
    known = {"run", "ckpt", "color_correct"}
    bad = [a for a in argv if "=" not in a or a.split("=", 1)[0] not in known]
    args = dict(a.split("=", 1) for a in argv if a not in bad)
    if bad or "run" not in args:
        log.error("%s (got %s)", USAGE, " ".join(argv) or "nothing")
        return 2
    if args.get("ckpt", "last") not in ("last", "best"):
        log.error("ckpt: expected last or best, got %s", args["ckpt"])
        return 2
    colour = args.get("color_correct", "false").lower()
    if colour not in ("true", "false"):
        log.error("color_correct: expected true or false, got %s", args["color_correct"])
        return 2
    try:
        metrics = evaluate_run(Path(args["run"]), ckpt=args.get("ckpt", "last"),
                               color_correct=colour == "true")
    except InputError as e:
        log.error("%s", e)
        return 2
    log.info("%s", json.dumps(metrics, indent=1))
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    raise SystemExit(main())
