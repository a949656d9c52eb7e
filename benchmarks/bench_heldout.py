"""Where held-out quality is lost: pose seen in training or not, time with a frame or between.

    python -m benchmarks heldout RUN_DIR [RUN_DIR ...] [--out FILE.md] [--threads 1]

For each finished run on a simulated scene (its ``.hydra/config.yaml`` and ``seg<k>/``
checkpoints), the trained model is rendered and scored against clean ground truth the
simulator renders on the spot (no sensor effects, area-averaged with the scene's
``frame_supersample``, as the stored held-out frames are), in a 2 × 2 design:

- **pose**: the training cameras (poses the model was fitted from) or the held-out
  camera (the ring position half-way between two training cameras);
- **time**: the RGB frame times (where the model also saw a frame) or the mid-points
  between consecutive frames (events only).

Each cell gives PSNR of the renders, PSNR of the empty field (the background alone) on
the same images, and their difference (the gain). The held-out × frame-time cell is the
run's own metric (all ground-truth times, every view). A gain that drops from the
training poses to the held-out pose is what the unseen viewpoint costs; a drop from frame
times to mid-times is what interpolating in time costs.

PSNR as the runs report it (:func:`eventrecon.evaluation.metrics.psnr`: the mean over images of
−10 log10 MSE, on the 8-bit-encoded images in [0, 1]).
"""

from __future__ import annotations

import argparse
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from eventrecon import TIME_SPAN
from eventrecon.common.colour import linear_to_srgb
from eventrecon.data.batcher import background_linear
from eventrecon.data.selection import heldout_split
from eventrecon.data.types import SplitData
from eventrecon.engine.build import load_dataset, load_segment, scene_properties
from eventrecon.engine.run_folder import run_config
from eventrecon.engine.segments import run_segments
from eventrecon.evaluation.heldout import encode, render_heldout
from eventrecon.evaluation.metrics import psnr
from eventrecon.sim.raytrace import PixelRenderer
from eventrecon.sim.spec import build_cameras, parse_spec

log = logging.getLogger("benchmarks.heldout")
#: Reads finished runs: ``python -m benchmarks`` alone does not run it.
NEEDS_RUNS = True


def mid_times(times: np.ndarray) -> np.ndarray:
    """Mid-points between consecutive frame times ``[F] -> [F-1]``.

    >>> mid_times(np.array([0.0, 100.0, 300.0])).tolist()
    [50.0, 200.0]
    """
    return 0.5 * (times[1:] + times[:-1])


def clean_truth(prend: PixelRenderer, times_u: np.ndarray) -> np.ndarray:
    """``[F, V, H, W, 3]`` clean ground truth in [0, 1] (sRGB-encoded 8 bit, as stored)."""
    t = torch.as_tensor(np.asarray(times_u, np.float64) / TIME_SPAN)
    per_view = [linear_to_srgb(prend.images(v, t).numpy()) for v in range(len(prend.cams))]
    return np.stack(per_view, axis=1).astype(np.float32) / 255.0


def score_cell(models, segments, split: SplitData, times_u: np.ndarray,
               prend: PixelRenderer) -> dict[str, float]:
    """Render every view of ``split`` at ``times_u`` and score against clean truth."""
    at = replace(split, frame_times=np.asarray(times_u, np.float64))
    views = list(range(len(split.cameras.names)))
    renders = render_heldout(models, segments, at, views, list(range(len(times_u))))
    pred = np.stack([[encode(renders[a, b]) for b in views] for a in range(len(times_u))])
    truth = clean_truth(prend, times_u)
    bg = encode(background_linear(split).clamp(0, 1).numpy())  # [V, H, W, 3]
    flat = truth.reshape(-1, *truth.shape[2:])
    p = psnr(pred.reshape(flat.shape), flat)
    e = psnr(np.broadcast_to(bg[None], truth.shape).reshape(flat.shape), flat)
    return {"psnr": p, "empty": e, "gain": p - e, "images": int(truth.shape[0] * truth.shape[1])}


def diagnose(run_dir: Path) -> dict[str, dict[str, float]]:
    """The 2 × 2 table (module docstring) of one run: ``{"train@frames": {...}, ...}``."""
    cfg = run_config(run_dir)
    ds = load_dataset(cfg)
    props = scene_properties(cfg, ds)
    segments = run_segments(cfg, props.segments)
    models = [(f.eval(), r) for f, r in
              (load_segment(cfg, props, run_dir / f"seg{k}") for k in range(len(segments)))]
    spec = parse_spec(cfg.scene)
    train_cams, held_cams = build_cameras(spec)
    train, held = ds.splits["train"], heldout_split(ds)
    frame_t = np.asarray(train.frame_times, np.float64)
    table = {}
    for pose, split, cams in (("train", train, train_cams), ("heldout", held, held_cams)):
        prend = PixelRenderer(spec.scene, cams, spec.frame_supersample)
        for when, times in (("frames", frame_t), ("between", mid_times(frame_t))):
            table[f"{pose}@{when}"] = score_cell(models, segments, split, times, prend)
            log.info("%s %s@%s: %s", run_dir.name, pose, when, table[f"{pose}@{when}"])
    return table


def markdown(rows: dict[str, dict[str, dict[str, float]]]) -> str:
    """One row per run and cell: PSNR, empty-field PSNR, gain."""
    lines = ["| run | pose | time | PSNR | empty | gain | images |",
             "|---|---|---|---|---|---|---|"]
    for run, table in rows.items():
        for key, c in table.items():
            pose, when = key.split("@")
            lines.append(f"| {run} | {pose} | {when} | {c['psnr']:.2f} | {c['empty']:.2f} "
                         f"| {c['gain']:+.2f} | {c['images']} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks heldout", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="finished run folders (simulated scenes)")
    ap.add_argument("--out", type=Path, help="write the Markdown table here")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    rows = {}
    for run in args.runs:
        with torch.no_grad():
            rows[str(run)] = diagnose(run)
    text = markdown(rows)
    log.info("\n%s", text)
    if args.out:
        args.out.write_text(text)
