"""What the occupancy grid keeps on a trained run: samples per ray by level, and what
other thresholds or grid shapes would keep, at what held-out PSNR.

    python -m benchmarks skip RUN_DIR [--thresholds 0.1 1] [--grids 32x16:1,0 32x16:0,0]
                                      [--batches 20] [--out FILE.md] [--threads 2]

For the first segment of a finished run (its ``.hydra/config.yaml`` and
``seg0/checkpoints/last.ckpt``), each row renders ``--batches`` training batches (the
run's ``n_rays``, its own ray sampler, perturbed, under the run's image autocast, with
gradients on, so the field sees what it sees in training and the count is the logged
``train/samples_per_ray``) and the held-out view at every frame time:

- the grid as trained;
- the same grid with each threshold of ``--thresholds`` (the trained moving maxima,
  another cut);
- each grid of ``--grids`` (``R x B : s, b``: ``R³`` cells, ``B`` time bins, dilation
  ``s`` cells in space and ``b`` bins in time), rebuilt on the trained field by
  ``--passes`` updates that ask every cell once each (one jittered point, the maximum
  kept, no decay) at the run's threshold;
- ``render.skip=none``.

Samples per ray are the field's inputs per rendered ray (a ray's three renders count
three), split into the coarse level (the same batches rendered with ``n_fine = 0``: the
coarse draws come first, so they are the same) and the fine level. "Opaque" is the share
of rendered rays whose opacity exceeds 0.5: their fine samples sit on the subject, in
occupied cells, so they reach the field. "Faint" hits are rays that meet the cylinder
with a coarse opacity below 1e-4 (:func:`ray_samples`): the table gives their
share of the hits, their share of the fine level's field inputs, and the fine inputs per
faint and per other hit. Session 49 used it to find that the grid's
dilation in time, not fog above the threshold, keeps most samples of a trained
`make train` run (``docs/results/history.md``).
"""

from __future__ import annotations

import argparse
import logging
import math
import time
from collections.abc import Sequence
from pathlib import Path
from unittest import mock

import torch
from torch import Tensor

from eventrecon.build import load_dataset, load_segment, scene_properties
from eventrecon.data.batcher import RayBatcher
from eventrecon.data.selection import heldout_split, training_split
from eventrecon.evaluate import render_heldout, run_config, score_images
from eventrecon.fields.base import Field
from eventrecon.render.clipping import INSIDE_TOL
from eventrecon.render.occupancy import OccupancyGrid
from eventrecon.render.occupancy_refined import RefinedGrid
from eventrecon.render.volume import Renderer
from eventrecon.segments import run_segments

log = logging.getLogger("benchmarks.skip")
#: Reads finished runs: ``python -m benchmarks`` alone does not run it.
NEEDS_RUNS = True


def parse_grid(text: str) -> tuple[int, int, tuple[int, int]]:
    """``"RxB:s,b"`` → ``(R, B, (s, b))``.

    >>> parse_grid("32x16:1,0")
    (32, 16, (1, 0))
    """
    try:
        shape, dil = text.split(":")
        res, bins = (int(v) for v in shape.split("x"))
        s, b = (int(v) for v in dil.split(","))
    except ValueError as exc:
        raise SystemExit(f"--grids: {text!r} is not RxB:s,b (e.g. 32x16:1,0)") from exc
    return res, bins, (s, b)


def ray_samples(renderer: Renderer, field: Field, batches: Sequence[dict],
                cut: float = 1e-4) -> dict[str, float]:
    """Field inputs per rendered ray over ``batches``, by level, and where the fine
    level's go.

    Each batch renders at its ``t0, t1, t_ref`` (shared coarse samples, generator seeded
    by its index) with gradients on, as in training: the coarse march then calls the field
    on every occupied sample and applies its stops as masks, so ``coarse + fine`` is the
    logged ``train/samples_per_ray``. The batches render twice, with ``n_fine = 0`` (the
    coarse draws come first, so they are the same) and as configured.

    Returns ``coarse``, ``fine`` (per rendered ray), ``opaque`` (the share of rendered
    rays whose final opacity exceeds 0.5) and, over the rays that meet the cylinder, by
    the coarse opacity of the ray (below ``cut``: *faint*): ``faint`` (their share),
    ``faint_fine`` (their share of the fine level's inputs), ``fine_faint`` /
    ``fine_other`` (fine inputs per faint / other ray); NaN without a fine level. The
    fine inputs are counted per ray at the renderer's last field query of each render
    (its fine level): all ``n_fine`` samples without a grid, else those in occupied cells,
    inside the cylinder and in front of the coarse stop. A faint ray's fine samples are
    spread by the coarse weights plus the sampler's ``ε`` where the coarse level found next
    to nothing."""
    counts: list[Tensor] = []
    query = renderer._query

    def watched(f: Field, o: Tensor, d: Tensor, t: Tensor, s: Tensor,
                keep: Tensor | None = None) -> tuple[Tensor, Tensor]:
        if keep is None:                         # Renderer._query's count, per ray
            counts.append(torch.full(s.shape[:1], s.shape[1], device=s.device))
        else:
            pts = o[:, None, :] + s[..., None] * d[:, None, :]
            inside = renderer.cylinder.inside(pts, renderer.clip_scale, tol=INSIDE_TOL)
            counts.append((keep & inside).sum(-1))
        return query(f, o, d, t, s, keep)

    inputs, opacity, fine_in = [], [], []
    n_fine, compiled = renderer.n_fine, renderer.compiled
    renderer.compiled = False    # PyTorch's passes, whose _query is watched (the same samples)
    try:
        for fine in (0, n_fine):
            renderer.n_fine, renderer.field_inputs, rays, opaque = fine, 0, 0, 0
            for i, batch in enumerate(batches):
                o, d = batch["rays_o"].repeat(3, 1), batch["rays_d"].repeat(3, 1)
                t = torch.cat([batch["t0"], batch["t1"], batch["t_ref"]], 0)
                counts.clear()
                with (torch.enable_grad(), renderer.image_autocast(o.device),
                      mock.patch.object(renderer, "_query", watched)):
                    out = renderer(field, o, d, t, batch["bg"].repeat(3, 1), perturb=True,
                                   gen=torch.Generator().manual_seed(i), copies=3)
                opaque += int((out[-1]["opacity"].detach() > 0.5).sum())
                rays += o.shape[0]
                if fine and counts:              # no hit: no query
                    hit = renderer.cylinder.ray_interval(o, d)[2]
                    opacity.append(out[0]["opacity"].detach()[hit])
                    fine_in.append(counts[-1].float().cpu())
            inputs.append(renderer.field_inputs / max(rays, 1))
    finally:
        renderer.n_fine, renderer.compiled = n_fine, compiled
    row = {"coarse": inputs[0], "fine": inputs[1] - inputs[0], "opaque": opaque / max(rays, 1)}
    op = torch.cat(opacity).cpu() if opacity else torch.zeros(0)
    kf = torch.cat(fine_in) if fine_in else torch.zeros(0)
    if not n_fine or op.numel() == 0:
        return row | dict.fromkeys(("faint", "faint_fine", "fine_faint", "fine_other"),
                                   math.nan)
    faint = op < cut
    return row | {"faint": float(faint.float().mean()),
                  "faint_fine": float(kf[faint].sum() / kf.sum().clamp(min=1)),
                  "fine_faint": float(kf[faint].mean()) if faint.any() else 0.0,
                  "fine_other": float(kf[~faint].mean()) if (~faint).any() else 0.0}


def rebuilt_grid(renderer: Renderer, field: Field, resolution: int, time_bins: int,
                 dilation: tuple[int, int], threshold: float, passes: int) -> OccupancyGrid:
    """A grid of another shape over the renderer's box, filled from ``field`` by
    ``passes`` updates that ask every cell (the running maximum, no decay)."""
    grid = OccupancyGrid(*renderer.cylinder.box(), resolution=resolution, time_bins=time_bins,
                         threshold=threshold, decay=1.0, fraction=1.0, recheck=1.0,
                         dilation=dilation)
    gen = torch.Generator().manual_seed(0)
    for _ in range(passes):
        grid.update(lambda x, t: renderer.masked_density(field, x, t), gen)
    return grid


def survey(run_dir: Path, thresholds: Sequence[float], grids: Sequence[str], n_batches: int,
           passes: int) -> list[dict]:
    """One row per grid setting (module docstring) for ``run_dir``'s first segment."""
    shapes = [parse_grid(text) for text in grids]      # a typo fails before any work
    cfg = run_config(run_dir)
    ds = load_dataset(cfg)
    props = scene_properties(cfg, ds)
    segments = run_segments(cfg, props.segments)
    field, renderer = load_segment(cfg, props, run_dir / "seg0")
    trained = renderer.occupancy
    if trained is None:
        raise SystemExit(f"{run_dir}: trained with render.skip=none (no grid to survey)")
    train = training_split(ds, cfg.data.views, cfg.data.fps, props.duration_s, (0.0, 1000.0))
    batcher = RayBatcher(train, segments[0], props.decay, props.bayer, cfg.data.neg_ratio)
    batches = [batcher.sample(int(cfg.trainer.n_rays), torch.Generator().manual_seed(i))
               for i in range(n_batches)]
    held = heldout_split(ds)
    frames = list(range(len(held.frame_times)))

    def row(name: str, grid: OccupancyGrid | None) -> dict:
        renderer.occupancy = grid
        counted = ray_samples(renderer, field, batches)
        t0 = time.perf_counter()
        img = render_heldout([(field, renderer)], segments[:1], held, [0], frames)
        sec = time.perf_counter() - t0
        score = score_images([img[f, 0] for f in frames], [held.frames[f, 0] for f in frames],
                             lpips=False)
        out = {"grid": name, **counted,
               "psnr": score["psnr"],
               "occupied": grid.occupied_fraction() if grid is not None else 1.0,
               "render_s": sec}
        log.info("%s %s: %.2f + %.2f samples per ray (%.3f of the rays opaque), occupied "
                 "%.3f, PSNR %.3f (%.1f s); faint rays %.3f of the hits, %.3f of the fine "
                 "inputs (%.1f fine per faint ray, %.1f per other)", run_dir.name, name,
                 out["coarse"], out["fine"], out["opaque"], out["occupied"], out["psnr"], sec,
                 out["faint"], out["faint_fine"], out["fine_faint"], out["fine_other"])
        return out

    def shape(g: OccupancyGrid) -> str:
        tau = float(g.effective_threshold())       # min(threshold, mean asked density)
        cut = f"threshold {g.threshold:g}" + (f" (effective {tau:.3g})"
                                              if tau < g.threshold * (1 - 1e-6) else "")
        refined = (f", refined {g.refine[0]}×/{g.refine[1]}× (dilation "
                   f"{g.refine_dilation[0]},{g.refine_dilation[1]})"
                   if isinstance(g, RefinedGrid) else "")
        return (f"{g.resolution}³×{g.time_bins}, dilation {g.dilation[0]},{g.dilation[1]}"
                f"{refined}, {cut}")

    rows = [row(f"as trained: {shape(trained)}", trained)]
    base = trained.threshold
    for thr in thresholds:
        trained.threshold = float(thr)
        trained.refresh()
        rows.append(row(f"as trained: {shape(trained)}", trained))
    trained.threshold = base
    trained.refresh()
    for res, bins, dil in shapes:
        grid = rebuilt_grid(renderer, field, res, bins, dil, base, passes)
        rows.append(row(f"rebuilt: {shape(grid)}", grid))
    rows.append(row("render.skip=none", None))
    return rows


def markdown(rows: dict[str, list[dict]]) -> str:
    """One line per run and grid setting."""
    lines = ["| run | grid | samples per ray: coarse + fine = all | opaque rays | occupied "
             "| faint hits: share; of the fine inputs | fine per faint / other hit "
             "| held-out PSNR | held-out render (s) |", "|---|---|---|---|---|---|---|---|---|"]
    for run, table in rows.items():
        for r in table:
            lines.append(f"| {run} | {r['grid']} | {r['coarse']:.2f} + {r['fine']:.2f} = "
                         f"{r['coarse'] + r['fine']:.2f} | {r['opaque']:.3f} | "
                         f"{r['occupied']:.3f} | {r['faint']:.3f}; {r['faint_fine']:.3f} | "
                         f"{r['fine_faint']:.1f} / {r['fine_other']:.1f} | "
                         f"{r['psnr']:.3f} | {r['render_s']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks skip", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="finished run folders (render.skip=grid)")
    ap.add_argument("--thresholds", nargs="*", type=float, default=[0.1, 1.0])
    ap.add_argument("--grids", nargs="*", default=["32x8:1,1", "32x16:1,0", "32x16:0,0"],
                    help="rebuilt grids, RxB:s,b")
    ap.add_argument("--batches", type=int, default=20)
    ap.add_argument("--passes", type=int, default=8, help="updates that fill a rebuilt grid")
    ap.add_argument("--out", type=Path, help="write the Markdown table here")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    rows = {str(run): survey(run, args.thresholds, args.grids, args.batches, args.passes)
            for run in args.runs}
    text = markdown(rows)
    log.info("\n%s", text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
