"""Quality per second of the backbone zoo, with and without empty-space skipping.

    python -m benchmarks zoo                                  # quick check: 10 and 30 s
    python -m benchmarks zoo --budgets 60 180 600 --out docs/results/zoo.md   # issue 12
    python -m benchmarks zoo --only ngp --skip grid --budgets 5 10 --images 1 --threads 1
    python -m benchmarks zoo --device cuda --budgets 60 180 600          # paper settings

For every backbone (``nerf``, ``ngp``, ``tensorf_cp``, ``hexplane``) and every
``render.skip`` (``none``, ``grid``), in one process:

1. **Training** (``eventrecon.engine.runner.run``) on ``scene=spheres`` at ``scale=cpu`` (CPU: 256
   rays, 32 + 32 samples, the CPU sizes, warm-up schedules compressed to the preset's
   1000 steps and kept there) or ``trainer=paper`` (``--device cuda``: 1024 rays, 64 + 128
   samples, the 8×256 MLP and the configs' own sizes, the paper's schedules), until
   ``max(--budgets)`` seconds of *training* (the held-out monitor's clock, which
   excludes evaluation; the occupancy-grid updates are added to it, see
   :class:`benchmarks.zoo_run.BudgetStop`). **PSNR@b** is the held-out PSNR of the last
   ``curve.csv`` row with ``wall_s <= b`` (all 96×72 pixels of the held-out view at three
   times; a row is written a step or two before each budget; "—": none); ``steps`` is
   the steps trained in the whole budget.
2. **Render**: ``renderer.render_image`` of the trained field on a 346×260 camera of the
   scene's ring rig (``eventrecon.render.cameras.ring_rig``), median seconds over
   ``--images`` images (views and times differ), and the field samples per pixel.
3. **Step**: from the trained state, ``--warmup`` + ``--reps`` real training steps
   alternating with the bare field step on the very samples each real step sent
   (:func:`benchmarks.zoo_run.time_steps`): medians of the real step, of the field's
   forward + backward, of its AdamW step, and the rest (sampling, compositing, losses);
   the grid update's seconds divided by ``render.occupancy.every`` (its per-step share,
   not in the real step); and the **samples per ray** reaching the field (field inputs
   of a real step / (3 · n_rays): every ray is rendered at t0, t1 and t_ref).

4. **Time to the reference PSNR** (issue 12: each backbone at its 1000-step ``scale=cpu``
   PSNR in ≤ ⅓ of the time): the ``skip=none`` run's PSNR at step ``--ref-step`` (1000, the
   preset's length) and the training time it took, then the time the ``skip=grid`` run
   first reaches that PSNR. Both read the curve as the median of its last five points
   (:func:`eventrecon.report.curves.time_to_level`); single points scatter by ~0.5 dB.

The result is a Markdown table (logged; ``--out FILE`` writes it, ``--json FILE`` the raw
rows, each run's held-out curve included), a second table of ratios ``none / grid``
measured in the same run and a third of the times to the reference PSNR. Runs go to a
temporary folder (``--work-dir``; removed unless ``--keep``). The default budgets are a
quick check (a few minutes per backbone); the issue's figures are ``--budgets 60 180 600``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import shutil
import tempfile
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from benchmarks.zoo_run import STATS_FILE, compose_run, time_render, time_steps
from eventrecon.data.selection import training_split
from eventrecon.engine import build, runner
from eventrecon.engine.segments import run_segments, run_window
from eventrecon.report.curves import time_to_level, trailing_median
from eventrecon.results.records import read_curve_rows

log = logging.getLogger("benchmarks.zoo")

#: name -> config overrides of the backbone (sizes come from the preset).
BACKBONES: dict[str, list[str]] = {
    "nerf": ["model=nerf"],
    "ngp": ["model=ngp"],
    "tensorf_cp": ["model=tensorf_cp"],
    "hexplane": ["model=hexplane"],
}
SKIPS: tuple[str, ...] = ("none", "grid")
#: The curve of a row without one (rows written before the curves were kept).
NO_CURVE: dict[str, list[float]] = {"wall_s": [], "step": [], "psnr": []}


def psnr_at(curve: Path, budgets: list[float]) -> dict[float, tuple[float | None, int | None]]:
    """``(psnr, step)`` of the last row of ``curve`` with ``wall_s <= b`` per budget ``b``
    (of two rows at the same time, the cheap one: every budget's PSNR is then pooled over
    the same pixels the same way)."""
    rows = read_curve_rows(curve) if curve.exists() else []
    out: dict[float, tuple[float | None, int | None]] = {}
    for b in budgets:
        inside = [r for r in rows if float(r["wall_s"]) <= b and r["psnr"]]
        last = max(inside, key=lambda r: (float(r["wall_s"]), int(r["step"]),
                                          r["kind"] == "cheap"), default=None)
        out[b] = (float(last["psnr"]), int(last["step"])) if last else (None, None)
    return out


def bench_one(name: str, skip: str, args: argparse.Namespace, work: Path) -> dict[str, Any]:
    """Train one backbone with one skip mode for the budgets, then time its trained state."""
    preset = "paper" if args.device == "cuda" else "cpu"
    cfg = compose_run([*BACKBONES[name], f"render.skip={skip}", *args.override], args.budgets,
                      preset, args.data_dir, args.curve_every,
                      args.safety * max(args.budgets) + 300)
    out_dir = work / f"{name}-{skip}"
    metrics = runner.run(cfg, out_dir)
    seg_dir = out_dir / "seg0"
    stats = json.loads((seg_dir / STATS_FILE).read_text())
    row: dict[str, Any] = {"backbone": name, "skip": skip, "status": metrics.get("status"),
                           "steps": int(metrics.get("steps", 0)),
                           "train_s": float(stats["wall_s"] or 0.0),
                           "updates_s": float(stats["update_s"])}
    for b, (p, s) in psnr_at(out_dir / "curve.csv", args.budgets).items():
        row[f"psnr@{b:g}"], row[f"step@{b:g}"] = p, s
    row["curve"] = cheap_curve(out_dir / "curve.csv")
    # the trained state, back from the run's last checkpoint
    ds = build.load_dataset(cfg)
    props = build.scene_properties(cfg, ds)
    window = run_window(cfg)
    train = training_split(ds, cfg.data.views, cfg.data.fps, props.duration_s,
                           window or (0.0, 1000.0))
    seg = run_segments(cfg, props.segments)[0]
    device = torch.device(args.device)
    module = build.build_module(cfg, props, train, seg, device=device)
    field, renderer = build.load_segment(cfg, props, seg_dir)
    module.field, module.renderer = field.train(), renderer
    module.to(device)  # also sets module.device, which the timings synchronise on
    step0 = build.inspect_checkpoint(seg_dir / "checkpoints" / "last.ckpt", field).step
    row.update(time_render(module, cfg, args.images))
    row.update(time_steps(module, max(step0, 0), args.warmup, args.reps, int(cfg.seed)))
    return row


def cheap_curve(curve: Path) -> dict[str, list[float]]:
    """The run's held-out curve points of one kind (``cheap``: the same pixels at every
    point), in time order: ``{"wall_s": […], "step": […], "psnr": […]}``."""
    rows = read_curve_rows(curve) if curve.exists() else []
    rows = sorted((r for r in rows if r["kind"] == "cheap" and r["psnr"]),
                  key=lambda r: (float(r["wall_s"]), int(r["step"])))
    return {"wall_s": [float(r["wall_s"]) for r in rows],
            "step": [float(r["step"]) for r in rows],
            "psnr": [float(r["psnr"]) for r in rows]}


def reference_time(none: dict[str, list[float]], grid: dict[str, list[float]],
                   ref_step: int, window: int = 5) -> dict[str, float | None]:
    """``skip=none``'s PSNR at its first curve point at or after ``ref_step`` (the median of
    its last ``window`` points, :func:`~eventrecon.report.curves.trailing_median`) and the
    training time to it, and the time ``skip=grid`` first reaches that PSNR (the same way);
    ``None`` where a curve never gets there."""
    out: dict[str, float | None] = {"psnr": None, "none_s": None, "grid_s": None}
    steps = np.asarray(none["step"], float)
    at = np.flatnonzero(steps >= ref_step)
    if at.size:
        out["psnr"] = float(trailing_median(np.asarray(none["psnr"]), window)[at[0]])
        out["none_s"] = float(none["wall_s"][at[0]])
        out["grid_s"] = time_to_level(np.asarray(grid["wall_s"]), np.asarray(grid["psnr"]),
                                      out["psnr"], window)
    return out


def _f(v: float | None, fmt: str) -> str:
    return "—" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, fmt)


def _pairs(rows: list[dict[str, Any]]) -> list[tuple[str, dict[str, Any], dict[str, Any]]]:
    """``(backbone, none row, grid row)`` of every backbone run in both modes."""
    out = []
    for name in dict.fromkeys(r["backbone"] for r in rows):
        pair = {r["skip"]: r for r in rows if r["backbone"] == name}
        if set(pair) == set(SKIPS):
            out.append((name, pair["none"], pair["grid"]))
    return out


def markdown(rows: list[dict[str, Any]], budgets: list[float], meta: dict[str, Any],
             ref_step: int = 1000) -> str:
    """The results table, the ``none / grid`` ratio table, the times to ``skip=none``'s
    PSNR at ``ref_step`` (:func:`reference_time`) and a line of run settings; the two
    comparisons only where some backbone ran with both skip modes."""
    head = (["backbone", "skip", "steps"] + [f"PSNR@{b:g}s" for b in budgets]
            + ["samples/ray", "real step ms", "field fwd+bwd ms", "AdamW ms", "rest ms",
               "grid upd. ms/step", "346×260 render s", "render samples/px"])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        name = r["backbone"] + ("" if r.get("status") == "ok" else f" ({r.get('status')})")
        cells = [name, r["skip"], str(r["steps"])]
        cells += [_f(r.get(f"psnr@{b:g}"), ".2f") for b in budgets]
        cells += [_f(r["samples_per_ray"], ".1f")]
        cells += [_f(r[k] * 1e3, ".1f") for k in ("real_s", "field_s", "optim_s", "rest_s",
                                                   "update_s_per_step")]
        cells += [_f(r["render_s"], ".2f"), _f(r["render_samples_per_px"], ".1f")]
        lines.append("| " + " | ".join(cells) + " |")
    pairs = _pairs(rows)
    if pairs:                                # both skip modes of some backbone
        lines += _comparisons(pairs, ref_step)
    lines += ["", "Settings: " + ", ".join(f"{k}={v}" for k, v in meta.items())]
    return "\n".join(lines)


def _comparisons(pairs: list[tuple[str, dict[str, Any], dict[str, Any]]],
                 ref_step: int) -> list[str]:
    """The ``none / grid`` ratio table and the times to ``skip=none``'s PSNR at
    ``ref_step`` of the backbones run in both modes (Markdown lines)."""
    lines: list[str] = []
    ratio_head = ["backbone", "samples/ray", "real step", "step + grid upd.", "render",
                  "steps in budget"]
    lines += ["", "Ratios none / grid (same run; > 1: skipping is faster or uses fewer):", "",
              "| " + " | ".join(ratio_head) + " |", "|" + "---|" * len(ratio_head)]
    for name, n, g in pairs:
        full = (n["real_s"] + n["update_s_per_step"]) / (g["real_s"] + g["update_s_per_step"])
        cells = [name, _f(n["samples_per_ray"] / g["samples_per_ray"], ".2f"),
                 _f(n["real_s"] / g["real_s"], ".2f"), _f(full, ".2f"),
                 _f(n["render_s"] / g["render_s"], ".2f"),
                 _f(g["steps"] / max(n["steps"], 1), ".2f")]
        lines.append("| " + " | ".join(cells) + " |")
    ref_head = ["backbone", f"none: PSNR at step {ref_step}", "in s", "grid: reaches it in s",
                "grid ÷ none (issue 12: ≤ 0.33)"]
    lines += ["", f"Time to `skip=none`'s PSNR at step {ref_step} (medians of the last five "
              "curve points):", "", "| " + " | ".join(ref_head) + " |",
              "|" + "---|" * len(ref_head)]
    for name, n, g in pairs:
        ref = reference_time(n.get("curve", NO_CURVE), g.get("curve", NO_CURVE), ref_step)
        ratio = (ref["grid_s"] / ref["none_s"] if ref["grid_s"] is not None
                 and ref["none_s"] else None)
        lines.append("| " + " | ".join([name, _f(ref["psnr"], ".2f"), _f(ref["none_s"], ".0f"),
                                        _f(ref["grid_s"], ".0f"), _f(ratio, ".2f")]) + " |")
    return lines


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks zoo",
                                 description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n".join(__doc__.splitlines()[1:]))
    ap.add_argument("--budgets", type=float, nargs="+", default=[10.0, 30.0],
                    help="training seconds at which PSNR is read (default: a quick 10 30; "
                         "issue 12: 60 180 600)")
    ap.add_argument("--only", nargs="+", choices=list(BACKBONES), help="subset of backbones")
    ap.add_argument("--skip", nargs="+", choices=SKIPS, default=list(SKIPS),
                    help="render.skip values")
    ap.add_argument("--images", type=int, default=3, help="346x260 images timed (median)")
    ap.add_argument("--warmup", type=int, default=3, help="steps before the timed ones")
    ap.add_argument("--reps", type=int, default=7, help="timed real and bare steps")
    ap.add_argument("--curve-every", type=int, default=50,
                    help="steps between held-out curve points (besides one per budget)")
    ap.add_argument("--ref-step", type=int, default=1000,
                    help="step of skip=none's reference PSNR (the third table; 1000: the "
                         "scale=cpu length)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                    help="cuda: the paper's settings (trainer=paper) on the GPU")
    ap.add_argument("--data-dir", default="data")
    ap.add_argument("--override", nargs="*", default=[],
                    help="extra Hydra overrides for every run (e.g. render.occupancy.every=8)")
    ap.add_argument("--safety", type=float, default=4.0,
                    help="Lightning max_time = SAFETY * max budget + 300 s (a backstop)")
    ap.add_argument("--work-dir", default=None, help="parent of the runs' folder (default: tmp)")
    ap.add_argument("--keep", action="store_true", help="keep the runs' folders")
    ap.add_argument("--out", help="write the Markdown table here")
    ap.add_argument("--json", help="write the raw rows here")
    args = ap.parse_args(argv if argv is not None else [])
    if args.device == "cuda" and not torch.cuda.is_available():
        log.info("zoo: --device cuda skipped: CUDA is not available on this machine")
        return
    torch.set_num_threads(args.threads)
    logging.getLogger("lightning").setLevel(logging.WARNING)
    logging.getLogger("lightning.pytorch").setLevel(logging.WARNING)
    logging.getLogger("baselines").setLevel(logging.WARNING)  # grid growth lines
    warnings.filterwarnings("ignore", module=r"lightning(\.|$)")
    work = Path(tempfile.mkdtemp(prefix="zoo-", dir=args.work_dir))
    rows = []
    try:
        for name in args.only or list(BACKBONES):
            for skip in args.skip:
                row = bench_one(name, skip, args, work)
                rows.append(row)
                log.info("%-10s skip=%-4s %5d steps  %s  %.1f samples/ray  step %.0f ms "
                         "(field %.0f + AdamW %.0f + rest %.0f, grid upd. %.0f/step)  "
                         "render %.2f s", name, skip, row["steps"],
                         "  ".join(f"PSNR@{b:g}={_f(row[f'psnr@{b:g}'], '.2f')}"
                                   for b in args.budgets),
                         row["samples_per_ray"], row["real_s"] * 1e3, row["field_s"] * 1e3,
                         row["optim_s"] * 1e3, row["rest_s"] * 1e3,
                         row["update_s_per_step"] * 1e3, row["render_s"])
    finally:
        if args.keep:
            log.info("runs kept in %s", work)
        else:
            shutil.rmtree(work, ignore_errors=True)
    meta = {"device": args.device, "preset": "trainer=paper" if args.device == "cuda"
            else "scale=cpu", "threads": args.threads, "budgets_s": args.budgets,
            "images": args.images, "reps": args.reps, "torch": torch.__version__,
            "loadavg": tuple(round(x, 2) for x in os.getloadavg())}
    if args.override:
        meta["overrides"] = " ".join(args.override)
    table = markdown(rows, args.budgets, meta, args.ref_step)
    log.info("\n%s", table)
    if args.out:
        Path(args.out).write_text(table + "\n")
    if args.json:
        Path(args.json).write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))


if __name__ == "__main__":
    import sys

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("eventrecon").setLevel(logging.WARNING)
    main(sys.argv[1:])
