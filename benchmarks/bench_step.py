"""The project's real training step per backbone, against the bare field step.

    python -m benchmarks step                      # every backbone, trainer=cpu, 2 threads
    python -m benchmarks step --only ngp --profile # where the time of one step goes
    python -m benchmarks step --only hexplane hexplane_torch   # the kernel against torch

A *real* step is what :class:`eventrecon.engine.module.EventNeRFModule` does each iteration:
draw the batch (window, balanced rays, event lookups, reference frame), render every
ray at ``t0, t1, t_ref`` with the coarse and fine passes, the four losses, backward and
the optimiser step. Its throughput is counted in the samples the field actually
evaluates (a forward hook counts them: rays that miss the clipping volume are not sent
to the field, so this is at most ``3 · n_rays · (n_coarse + n_fine)``). The *bare* step
is the field alone on as many random samples per step (forward, a trivial loss, backward,
optimiser step), as ``bench_fields`` measures it; ``real/bare`` is the share of the
field's own speed the whole step keeps (1 = the rest of the step costs nothing).
Scene: the default ``spheres`` at the ``trainer=cpu`` preset (simulated into ``data/`` if
missing). Medians over ``--reps`` steps after ``--warmup``.

``--grids`` sets the size of a growing field's grids (TensoRF-CP's lines): ``final``
(default), the size it trains at from the first few percent of a run on (``scale=cpu``:
from step ~67 of 1000), or ``initial``, the fresh field's (16 vertices).

Each grid backbone also runs as ``<backbone>_torch`` (``model.implementation=torch``:
the PyTorch reference everywhere, :mod:`eventrecon.kernels`) beside its default
(``auto``: the compiled CPU kernel where it applies), so that the kernel's share of the
real step can be read off the two rows.

``--skip`` sets ``render.skip`` (default ``none``: every sample of a ray that hits the
cylinder reaches the field, as the figures in ``docs/results/`` were taken). With
``--skip grid`` the occupancy grid is updated once from the fresh field before timing
(a run updates it every ``render.occupancy.every`` steps as the field learns); the
effect of skipping on a *trained* field is measured by ``python -m benchmarks zoo``.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir

from eventrecon.data.batcher import Segment
from eventrecon.engine import build
from eventrecon.engine.losses import total_loss
from eventrecon.engine.module import step_generator

log = logging.getLogger("benchmarks.step")
CONF = str(Path(__file__).resolve().parents[1] / "conf")

#: name -> config overrides (the CPU presets; ``nerf_paper`` is the paper's 8×256 MLP;
#: ``<backbone>_torch`` the backbone with ``model.implementation=torch``).
BACKBONES: dict[str, list[str]] = {
    "nerf": ["model=nerf"],
    "nerf_paper": ["model=nerf", "model.depth=8", "model.width=256", "model.skip=4"],
    "ngp": ["model=ngp"],
    "ngp_torch": ["model=ngp", "model.implementation=torch"],
    "tensorf_cp": ["model=tensorf_cp"],
    "tensorf_cp_torch": ["model=tensorf_cp", "model.implementation=torch"],
    "hexplane": ["model=hexplane"],
    "hexplane_torch": ["model=hexplane", "model.implementation=torch"],
}


def _median_time(fn: Callable[[], None], reps: int, warmup: int) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def measure(overrides: list[str], reps: int, warmup: int, data_dir: str,
            profile: bool = False, skip: str = "none", grids: str = "final") -> dict:
    """Median seconds of the real and the bare step of one backbone configuration
    (``grids``: a growing field at its ``final`` or ``initial`` size)."""
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(config_name="config", overrides=[*overrides, f"data_dir={data_dir}",
                                                        f"render.skip={skip}"])
    ds = build.load_dataset(cfg)
    props = build.scene_properties(cfg, ds)
    module = build.build_module(cfg, props, ds.splits["train"], Segment(0.0, 1000.0))
    plan = getattr(module.field, "plan", None)
    if grids == "final" and plan is not None and plan.n_stages > 1:
        module.field.upsample(plan.end)           # as GridGrowth leaves it
    opt = module.configure_optimizers()
    grid = module.renderer.occupancy
    if grid is not None:  # as OccupancyUpdate does at step 0
        with torch.no_grad():
            module.field.eval()
            grid.update(lambda x, t: module.renderer.masked_density(module.field, x, t),
                        torch.Generator().manual_seed(cfg.seed * 1_000_003))
            module.field.train()
    n_rays = int(cfg.trainer.n_rays)
    queried: list[int] = []
    hook = module.field.register_forward_hook(lambda m, inp, out: queried.append(len(inp[0])))
    state = {"step": 0}

    def optimise(loss: torch.Tensor) -> None:
        """The field's regulariser, backward and the optimiser step (both kinds of step)."""
        reg = module.field.regularization()
        if reg is not None:
            loss = loss + reg
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    def real() -> None:
        s = state["step"] = state["step"] + 1
        gen = step_generator(0, s)
        batch = module.batcher.sample(n_rays, gen)
        optimise(total_loss(module.render_three(batch, gen), batch, module.loss_cfg, s)["loss"])

    per_step = []
    for _ in range(5):  # the field samples of a real step (median over a few steps)
        queried.clear()
        real()
        per_step.append(sum(queried))
    samples = int(statistics.median(per_step))
    hook.remove()
    g = torch.Generator().manual_seed(0)
    xyz, t = torch.rand(samples, 3, generator=g) - 0.5, torch.rand(samples, 1, generator=g)

    def bare() -> None:
        sigma, rgb = module.field(xyz, t)
        optimise(sigma.mean() + rgb.mean())

    real_s = _median_time(real, reps, warmup)
    bare_s = _median_time(bare, reps, warmup)
    row = {"samples": samples, "real_s": real_s, "bare_s": bare_s,
           "real_samples_per_s": samples / real_s, "bare_samples_per_s": samples / bare_s}
    if profile:
        from torch.profiler import ProfilerActivity
        from torch.profiler import profile as torch_profile

        with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
            for _ in range(3):
                real()
        row["profile"] = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=12)
    return row


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks step",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", choices=list(BACKBONES), help="subset of backbones")
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--data-dir", default="data")
    ap.add_argument("--skip", choices=("none", "grid"), default="none",
                    help="render.skip (grid: updated once from the fresh field)")
    ap.add_argument("--grids", choices=("final", "initial"), default="final",
                    help="a growing field's grids at their final or initial size")
    ap.add_argument("--profile", action="store_true", help="print the top operators of 3 steps")
    args = ap.parse_args(argv if argv is not None else [])
    torch.set_num_threads(args.threads)
    for name, over in BACKBONES.items():
        if args.only and name not in args.only:
            continue
        r = measure(over, args.reps, args.warmup, args.data_dir, args.profile, args.skip,
                    args.grids)
        log.info("%-16s real %8.1f k samples/s (%6.1f ms/step)  bare %8.1f k samples/s "
                 "(%6.1f ms)  real/bare %.2f  [%d samples/step, %d threads, skip %s, grids "
                 "%s]", name,
                 r["real_samples_per_s"] / 1e3, r["real_s"] * 1e3,
                 r["bare_samples_per_s"] / 1e3, r["bare_s"] * 1e3,
                 r["real_samples_per_s"] / r["bare_samples_per_s"], r["samples"], args.threads,
                 args.skip, args.grids)
        if "profile" in r:
            log.info("%s", r["profile"])


if __name__ == "__main__":
    import sys

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("eventrecon").setLevel(logging.WARNING)
    main(sys.argv[1:])
