"""Held-out monitoring during training: accuracy-vs-time curve, TensorBoard, best checkpoint.

Two kinds of evaluation, both on the held-out views of the segment:

- *cheap* (every ``curve_every`` steps): PSNR on a fixed random subset of
  ``curve_pixels`` pixels of every held-out view at three ground-truth times of the
  segment (start, middle, end). SSIM/LPIPS need whole images and are left empty;
- *full* (every ``eval_every`` steps and at the end): whole images of every held-out
  view at those three times — PSNR, SSIM, LPIPS — plus TensorBoard images (render vs
  ground truth, opacity, depth, and for training view 0 and the last step's window the
  measured ``θ·E(t0, t1)`` beside the rendered ``L(Ĉ(t1)) − L(Ĉ(t0))`` of the pixel's
  channel).

Under DDP every rank evaluates (the checkpoint it may save is a collective call) and
only rank 0 writes ``curve.csv``; loggers are rank-0 only by themselves.

Wall-clock is the training time only: time spent inside this callback is subtracted,
so curves of different backbones compare training cost. Rows go to the segment's
``curve.csv`` (:class:`eventrecon.results.records.CurveLog`); renders are scored as the final
evaluation scores them (:func:`eventrecon.evaluation.heldout.score_images`); a full evaluation
that improves PSNR saves ``checkpoints/best.ckpt``.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch

from eventrecon.data.batcher import Segment, background_linear
from eventrecon.data.types import SplitData
from eventrecon.evaluation.heldout import cheap_psnr, encode, score_images
from eventrecon.results.records import CURVE_FILE, CurveLog

__all__ = ["HeldOutMonitor"]

log = logging.getLogger(__name__)


class HeldOutMonitor(L.Callback):
    """See module docstring.

    Args:
        split: the validation split (ground-truth frames and cameras).
        segment: the segment being trained (its times are the ones evaluated).
        out_dir: the segment's folder (``curve.csv`` and ``checkpoints/``).
        curve_every, eval_every, image_every: intervals in steps (≤ 0 disables).
        curve_pixels: pixels per view in a cheap evaluation.
        chunk: rays per chunk for full images.
        seed: picks the cheap-evaluation pixels.
    """

    def __init__(self, split: SplitData, segment: Segment, out_dir: Path, curve_every: int,
                 eval_every: int, image_every: int, curve_pixels: int, chunk: int,
                 seed: int = 0) -> None:
        self.split, self.segment, self.out_dir = split, segment, Path(out_dir)
        self.curve_every, self.eval_every, self.image_every = curve_every, eval_every, image_every
        self.chunk = chunk
        times = np.asarray(split.frame_times, dtype=np.float64)
        inside = np.flatnonzero((times >= segment.start) & (times <= segment.end))
        if inside.size == 0:
            inside = np.array([int(np.argmin(np.abs(times - segment.start)))])
        pick = np.unique(inside[np.round(np.linspace(0, inside.size - 1, 3)).astype(int)])
        self.frames = pick.tolist()
        cams = split.cameras
        g = torch.Generator().manual_seed(seed + 7)
        n_pix = cams.height * cams.width
        self.pix = torch.randperm(n_pix, generator=g)[: min(curve_pixels, n_pix)]
        self.bg = background_linear(split)
        self.best_psnr = -math.inf
        self.last_psnr: float | None = None  # the latest evaluation (progress reports)
        self.wall = 0.0  # this segment's training seconds (restored on resume)
        self._t_last: float | None = None
        self._full_at: int | None = None  # the step of the last full evaluation
        self.curve = CurveLog(self.out_dir / CURVE_FILE)

    # -------------------------------------------------------------- wall clock
    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """On resume, forget curve rows written after the checkpoint being resumed (the
        replayed steps log them again); rank 0 only, written atomically."""
        if trainer.is_global_zero:
            self.curve.truncate_after(int(trainer.global_step))

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule,
                             batch: Any, batch_idx: int) -> None:
        self._t_last = time.perf_counter()

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule,
                           outputs: Any, batch: Any, batch_idx: int) -> None:
        if self._t_last is not None:
            self.wall += time.perf_counter() - self._t_last
        step = int(trainer.global_step)
        if self.eval_every > 0 and step % self.eval_every == 0:
            self.evaluate(trainer, pl_module, full=True)
        elif self.curve_every > 0 and step % self.curve_every == 0:
            self.evaluate(trainer, pl_module, full=False)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """A full evaluation of the final model, unless the schedule just made one."""
        if self._full_at != int(trainer.global_step):
            self.evaluate(trainer, pl_module, full=True)

    def state_dict(self) -> dict[str, Any]:
        return {"wall": self.wall, "best_psnr": self.best_psnr}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self.wall = state_dict.get("wall", 0.0)
        self.best_psnr = state_dict.get("best_psnr", -math.inf)

    # -------------------------------------------------------------- evaluation
    @torch.no_grad()
    def evaluate(self, trainer: L.Trainer, pl_module: L.LightningModule, full: bool) -> dict:
        field, renderer = pl_module.field, pl_module.renderer
        was_training = field.training
        field.eval()
        cams, step = self.split.cameras, int(trainer.global_step)
        device = pl_module.device
        preds, gts, extras = [], [], []
        for f in self.frames:
            t = float(self.segment.normalise(float(self.split.frame_times[f])))
            t = min(1.0, max(0.0, t))
            for v in range(len(cams)):
                gt = self.split.frames[f, v]
                if full:
                    res = renderer.render_image(field, cams, v, t, self.bg[v].to(device),
                                                chunk=self.chunk)
                    preds.append(res["rgb"].clamp(0, 1).cpu().numpy())
                    gts.append(gt)
                    extras.append(res)
                else:
                    preds.append(self._render_pixels(field, renderer, v, t, device))
                    gts.append(gt.reshape(-1, 3)[self.pix.numpy()])
        field.train(was_training)
        if full:
            m = score_images(preds, gts, lpips=("alex",))     # the curve's LPIPS-Alex
            row = {"psnr": m["psnr"], "ssim": m["ssim"], "lpips": m.get("lpips")}
            n_views = len(cams)
            over_time = np.concatenate(  # view 0 at each evaluated time: render | truth
                [np.concatenate([encode(preds[i]), gts[i].astype(np.float32) / 255], 1)
                 for i in range(0, len(preds), n_views)], 0)
            self._log_images(trainer, pl_module, over_time, extras[0], step)
        else:
            row = {"psnr": cheap_psnr(preds, gts), "ssim": None, "lpips": None}
        self.last_psnr = row["psnr"]
        kind = "full" if full else "cheap"
        if full:
            self._full_at = step
        self._append_curve(step, row, kind, trainer)
        if trainer.logger is not None:
            trainer.logger.log_metrics(
                {f"val_{kind}/{k}": float(v) for k, v in row.items() if v is not None}, step)
            # accuracy against training seconds, live: the x axis is whole seconds
            trainer.logger.log_metrics({"val_vs_seconds/psnr": float(row["psnr"])},
                                       int(round(self.wall)))
        if full and row["psnr"] > self.best_psnr:
            self.best_psnr = row["psnr"]
            trainer.save_checkpoint(str(self.out_dir / "checkpoints" / "best.ckpt"),
                                    weights_only=False)
        return row

    def _render_pixels(self, field: Any, renderer: Any, v: int, t: float,
                       device: torch.device) -> np.ndarray:
        cams = self.split.cameras
        uv = cams.pixel_grid()[self.pix]
        view = torch.full((uv.shape[0],), v, dtype=torch.long)
        bg = self.bg[v].reshape(-1, 3)[self.pix]
        tt = torch.full((uv.shape[0], 1), t)
        with renderer.image_autocast(device):
            levels = renderer(field, cams, view, uv, tt.to(device), bg.to(device),
                              perturb=False)
        return levels[-1]["rgb"].float().clamp(0, 1).cpu().numpy()

    def _append_curve(self, step: int, row: dict, kind: str, trainer: L.Trainer) -> None:
        if trainer.is_global_zero:
            self.curve.append(self.wall, step, row, kind)

    def _log_images(self, trainer: L.Trainer, pl_module: Any, over_time: np.ndarray,
                    res: dict, step: int) -> None:
        """TensorBoard images: view 0's render beside its ground truth at each evaluated
        time (one row per time), its opacity and depth, and the measured vs rendered events."""
        exp = getattr(trainer.logger, "experiment", None)
        if exp is None or not hasattr(exp, "add_image"):
            return
        if self.image_every <= 0 or (step % self.image_every and step != trainer.max_steps):
            return
        exp.add_image("heldout/render_vs_gt", over_time, step, dataformats="HWC")
        exp.add_image("heldout/opacity", res["opacity"].cpu().numpy(), step, dataformats="HW")
        depth = res["depth"].cpu().numpy()
        exp.add_image("heldout/depth", depth / max(float(depth.max()), 1e-6), step,
                      dataformats="HW")
        exp.add_image("train/events_measured_vs_rendered", self._event_image(pl_module), step,
                      dataformats="HWC")

    @torch.no_grad()
    def _event_image(self, pl_module: Any) -> np.ndarray:
        """``[H, 2W, 3]``: measured ``θ·E(t0, t1)`` | rendered ``L(Ĉ(t1)) − L(Ĉ(t0))``.

        Training view 0, the last step's window, the log change of the channel each
        pixel sees (its Bayer channel, or the channel mean for grey event pixels); red
        for brighter, blue for darker, both panels on the same scale.
        """
        from eventrecon.engine.losses import log_intensity
        from eventrecon.events.bayer import bayer_mask

        batcher, renderer, field = pl_module.batcher, pl_module.renderer, pl_module.field
        cfg = pl_module.loss_cfg
        t0, t1 = pl_module.last_window
        seg = batcher.segment
        measured = cfg.theta * batcher.events.window_all(seg.units(t0), seg.units(t1))[0]
        was_training = field.training
        field.eval()
        bg = batcher.background[0]
        rgbs = [renderer.render_image(field, batcher.cameras, 0, t, bg, chunk=self.chunk)["rgb"]
                for t in (t0, t1)]
        field.train(was_training)
        if batcher.bayer:  # the channel each pixel sees
            mask = bayer_mask(*rgbs[0].shape[:2], device=rgbs[0].device)
            seen = [(rgb * mask).sum(-1) for rgb in rgbs]
        else:  # grey event pixels see the channel mean (as the losses)
            seen = [rgb.mean(-1) for rgb in rgbs]
        change = log_intensity(seen[1], cfg.eps) - log_intensity(seen[0], cfg.eps)
        panels = torch.cat([measured.to(change), change], dim=1).float().cpu().numpy()
        scale = max(float(np.abs(panels).max()), cfg.theta)
        return np.stack([np.clip(panels, 0, None), np.zeros_like(panels),
                         np.clip(-panels, 0, None)], -1) / scale
