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
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from eventrecon.data.batcher import Segment, background_linear
from eventrecon.data.types import SplitData, linear_to_srgb
from eventrecon.fields.base import Field
from eventrecon.render.volume import Renderer
from eventrecon.segments import crossfade_weights

__all__ = ["render_heldout", "evaluate_heldout", "write_renders", "main"]

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
    return out


def evaluate_heldout(renders_lin: np.ndarray, split: SplitData, views: Sequence[int],
                     frame_idx: Sequence[int], lpips: bool = True,
                     color_correct: bool = False) -> dict:
    """PSNR / SSIM / LPIPS of sRGB-encoded renders against the ground-truth PNGs.

    Also ``psnr_background``: the PSNR of the background alone (what a field with zero
    density everywhere renders) on the same frames. A run whose PSNR is close to it has
    learnt little of the scene; a low-contrast scene can score high with nothing in it.
    """
    from eventrecon.metrics import evaluate_images, psnr

    bg = linear_to_srgb(background_linear(split).clamp(0, 1).numpy()).astype(np.float32) / 255.0
    preds, gts, empty = [], [], []
    for a, f in enumerate(frame_idx):
        for b, v in enumerate(views):
            preds.append(linear_to_srgb(renders_lin[a, b]).astype(np.float32) / 255.0)
            gts.append(split.frames[f, v].astype(np.float32) / 255.0)
            empty.append(bg[v])
    result = evaluate_images(preds, gts, lpips=lpips, color_correct=color_correct)
    result["psnr_background"] = psnr(np.stack(empty), np.stack(gts))
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


USAGE = "usage: python -m eventrecon.evaluate run=DIR [ckpt=last|best] [color_correct=true]"


def main(argv: Sequence[str] | None = None) -> int:
    """CLI (see module docstring). Exit 0 done, 2 bad input (one line)."""
    from eventrecon.errors import InputError
    from eventrecon.runner import evaluate_run

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
    try:
        metrics = evaluate_run(Path(args["run"]), ckpt=args.get("ckpt", "last"),
                               color_correct=args.get("color_correct", "false").lower() == "true")
    except InputError as e:
        log.error("%s", e)
        return 2
    log.info("%s", json.dumps(metrics, indent=1))
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    raise SystemExit(main())
