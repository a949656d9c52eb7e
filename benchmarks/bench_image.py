"""A 346×260 evaluation image of the default job, timed with any commit's code.

    python -m benchmarks image                        # this checkout, untrained field
    python -m benchmarks image --run outputs/.../RUN  # the field of a finished run
    # the same image with an older commit's code (issue 12's literal comparison):
    git worktree add --detach /tmp/old 526830c
    PYTHONPATH=/tmp/old/src python benchmarks/bench_image.py --repo /tmp/old

Builds the field and the renderer of ``python train.py``'s configuration (``--override``
adds Hydra overrides) from the ``conf/`` of ``--repo`` (default: this checkout) with
whichever ``eventrecon`` Python imports, and renders ``--images`` full images, image ``i``
from view ``i mod 3`` of a three-camera ring at the scene's rig (``scene.rig``: radius,
elevation, field of view, target; ``--width``×``--height``) at time ``(i + 0.5)/n``,
after ``--warmup`` untimed ones, under the image autocast the run would use (bf16 on a
CPU with native bf16 at HEAD; the code of issue 12's filing commit renders in fp32). Logs
the median seconds per image and the field samples per pixel where the renderer counts
them.

Without ``--run`` the field is freshly initialised (seed 0): every ray is fog and an
occupancy grid, where there is one, starts fully occupied, so nothing is skipped -- the
worst case, and the case issue 12 measured (a 20-step run). ``--step N`` sets such a
field's training progress to step ``N`` (the NeRF's band-annealing window; ``--step 20``:
the issue's 20-step command with today's code, whose first bands are partly on; the
filing code annealed over a share of the run and had every band on); without it the
field is at step 0, where every band is off. With ``--run`` the field and
the grid come from the run's last checkpoint of its first segment (``seg0``), with the
run's own config and data properties (this checkout's code only; ``--override`` and
``--repo`` do not apply).

The code of older commits builds its field and renderer through ``eventrecon.engine.runner``
instead of ``eventrecon.engine.build``; both are handled here. That code also fails on a chunk
of rays none of which meets the clipping cylinder (the field is asked for zero rows), so
such a call returns empty outputs here without asking the field.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger("benchmarks.image")

HERE = Path(__file__).resolve().parent


def _config(repo: Path, overrides: list[str], run: Path | None) -> DictConfig:
    """The run's saved config (``run/.hydra/config.yaml``) or the default job's."""
    if run is not None:          # read directly: older commits lack run_folder.run_config
        path = run / ".hydra" / "config.yaml"
        if not path.is_file():
            from eventrecon.common.errors import InputError

            raise InputError(path, "<file>", "the run's saved Hydra config")
        return OmegaConf.load(path)
    with initialize_config_dir(config_dir=str(repo / "conf"), version_base="1.3"):
        return compose(config_name="config", overrides=["logger=none", *overrides])


def _field_and_renderer(cfg: DictConfig, run: Path | None) -> tuple[Any, Any]:
    """Field and renderer of ``cfg``, by the imported code's own builders (a run's: its
    ``seg0`` checkpoint, with the cylinder of its data)."""
    if run is not None:
        from eventrecon.engine import build
        props = build.scene_properties(cfg, build.load_dataset(cfg))
        return build.load_segment(cfg, props, run / "seg0")
    props = SimpleNamespace(cylinder=dict(cfg.scene.cylinder))
    if "render" in cfg:                    # this layout: a render group, eventrecon.engine.build
        from eventrecon.config.precision import run_precision
        from eventrecon.engine import build
        field = build.build_field(cfg.model)
        renderer = build.build_renderer(cfg.render, props, run_precision(cfg))
        field.set_scene_box(*renderer.cylinder.box())
        return field, renderer
    # the older layout, e.g. issue 12's filing commit
    from eventrecon.engine import runner
    return runner.build_field(cfg.model), runner.build_renderer(cfg, props)


def _guard_empty(field: Any) -> None:
    """Answer a call with zero rows with empty outputs (module docstring)."""
    forward = field.forward

    def guarded(xyz: torch.Tensor, t: torch.Tensor, *args: Any, **kwargs: Any) -> Any:
        if xyz.shape[0] == 0:
            return xyz.new_zeros(0), xyz.new_zeros(0, 3)
        return forward(xyz, t, *args, **kwargs)
    field.forward = guarded


def _sync(device: torch.device) -> None:
    """Wait for a CUDA device before reading the clock (nothing on the CPU)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_images(field: Any, renderer: Any, rig: dict, n: int, width: int, height: int,
                warmup: int = 1) -> dict[str, Any]:
    """Seconds per ``width``×``height`` image (view ``i mod 3`` of a three-camera ring at
    the scene's radius, elevation, field of view and target; time ``(i + 0.5)/n``; rays
    computed before the clock starts) and field samples per pixel where counted, after
    ``warmup`` untimed images (which load compiled kernels and build oneDNN's). Also
    ``bench_zoo``'s render timing (:func:`benchmarks.zoo_run.time_render`); a CUDA device
    is synchronised around each image."""
    from eventrecon.render.cameras import ring_rig
    cams = ring_rig(3, width, height, radius=float(rig.get("radius", 2.5)),
                    elevation_deg=float(rig.get("elevation_deg", 15.0)),
                    fov_deg=float(rig.get("fov_deg", 40.0)),
                    target=tuple(rig.get("target", (0.0, -0.25, 0.0))))
    for v in range(3):
        cams.image_rays(v)
    field.eval()
    device = next(iter(field.parameters())).device
    times, per_px = [], []
    with torch.no_grad():
        for i in range(warmup):
            renderer.render_image(field, cams, i % 3, 0.5)
        for i in range(n):
            if hasattr(renderer, "field_inputs"):
                renderer.field_inputs = 0
            _sync(device)
            t0 = time.perf_counter()
            renderer.render_image(field, cams, i % 3, (i + 0.5) / n)
            _sync(device)
            times.append(time.perf_counter() - t0)
            if hasattr(renderer, "field_inputs"):
                per_px.append(renderer.field_inputs / (width * height))
    return {"seconds": [round(t, 3) for t in times], "median_s": statistics.median(times),
            "samples_per_px": statistics.median(per_px) if per_px else None}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks image",
                                 description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n".join(__doc__.splitlines()[1:]))
    ap.add_argument("--repo", default=str(HERE.parent),
                    help="checkout whose conf/ gives the default job (default: this one)")
    ap.add_argument("--run", help="a finished run's folder: its field and grid")
    ap.add_argument("--override", nargs="*", default=[], help="Hydra overrides")
    ap.add_argument("--step", type=int, help="a fresh field's training step (band window)")
    ap.add_argument("--images", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=1, help="untimed images first")
    ap.add_argument("--width", type=int, default=346)
    ap.add_argument("--height", type=int, default=260)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", help="write the result here")
    args = ap.parse_args(argv if argv is not None else [])
    if args.images < 1 or args.warmup < 0:
        ap.error("--images must be at least 1 and --warmup at least 0")
    if args.run and (args.override or args.repo != ap.get_default("repo")
                     or args.step is not None):
        ap.error("--run renders the run's own field and config: --override, --repo and "
                 "--step do not apply")
    if args.step is not None and args.step < 0:
        ap.error("--step must be at least 0")
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    run = Path(args.run) if args.run else None
    cfg = _config(Path(args.repo).resolve(), args.override, run)
    field, renderer = _field_and_renderer(cfg, run)
    if args.step is not None:
        if not hasattr(field, "set_progress"):
            ap.error(f"--step: {type(field).__name__} has no training progress to set")
        field.set_progress(args.step)
    _guard_empty(field)
    row = time_images(field, renderer, dict(cfg.scene.get("rig") or {}), args.images,
                      args.width, args.height, args.warmup)
    import eventrecon
    row.update({"package": str(Path(eventrecon.__file__).parent), "run": args.run,
                "model": cfg.model.get("_target_"), "model_width": cfg.model.get("width"),
                "image": [args.width, args.height], "warmup": args.warmup, "step": args.step,
                "image_dtype": str(getattr(renderer, "image_dtype", None)),
                "threads": args.threads})
    log.info("%d×%d image: %.2f s (median of %s)%s  [%s]", args.width, args.height,
             row["median_s"], row["seconds"],
             "" if row["samples_per_px"] is None
             else f", {row['samples_per_px']:.1f} field samples per pixel", row["package"])
    if args.json:
        Path(args.json).write_text(json.dumps(row, indent=2))


if __name__ == "__main__":
    import sys

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("eventrecon").setLevel(logging.WARNING)
    main(sys.argv[1:])
