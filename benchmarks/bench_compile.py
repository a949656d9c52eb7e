"""``torch.compile`` (inductor) and bf16 autocast on the CPU against eager fp32, one run.

    python -m benchmarks compile                       # NeRF 4x128 (trainer=cpu), 2 threads
    python -m benchmarks compile --depth 8 --width 256 --skip 4 --batch 16384
    python -m benchmarks compile --no-step --threads 1 # the field step only
    python -m benchmarks compile --mode max-autotune   # inductor's GEMM autotuning

Two measurements, each variant starting from the same weights and seeing the same
inputs; after each variant's own warm-up, the variants' timed steps alternate (so they
see the same background load) and the median is reported. The warm-up (the first step
holds the compilation) is reported apart, with the number of graphs and graph breaks
dynamo made for that variant.

1. **Field step** of the NeRF MLP (:class:`eventrecon.fields.nerf.NeRFField`, no band
   annealing): forward on ``--batch`` random samples, MSE of ``σ`` and ``rgb`` to fixed
   random targets, backward, AdamW (lr 1e-4, weight decay 0.1). Variants: ``eager``
   (fp32), ``bf16`` (forward under ``torch.autocast("cpu", torch.bfloat16)``),
   ``compiled`` (``torch.compile(field)``), ``compiled_bf16``. Accuracy: for the eager
   variants the largest difference of the forward outputs to eager fp32 on the batch,
   before training (``σ`` relative to its largest value); for the compiled ones the
   first step's loss against eager's (same weights, same batch).
2. **Whole shared step** (``--no-step`` skips it): the project's real step on the
   ``spheres`` scene at ``trainer=cpu`` with ``render.skip=none`` (every sample of a hit
   ray reaches the field): batch, rendering at t0, t1, t_ref with both levels, the four
   losses, backward, AdamW. Variants: ``eager``; ``bf16`` (rendering and losses under
   autocast; compositing stays fp32 by design); ``compiled_field`` (``torch.compile(field,
   dynamic=True)``: the samples per step vary); ``compiled_step`` (rendering and losses
   as one ``torch.compile(..., dynamic=True)`` function; the batch drawing stays eager);
   ``compiled_step_bf16`` (that, under autocast).
   The loss is evaluated at a fixed step for every variant (the sparsity ramp's weight
   would otherwise be a new constant, and a recompilation, at every step). Accuracy:
   the first step's loss against eager's.

Compilation runs with an empty inductor cache (a temporary ``TORCHINDUCTOR_CACHE_DIR``,
removed at the end), so warm-up is the cost of a first run; ``--warm-cache`` uses the
default cache instead (what later runs on the same machine pay; kernels of an earlier
run, even of another network size under ``dynamic=True``, are then reused). Kernels
compiled by one variant may still be reused by a later variant of the same run.

If inductor fails (no C++ compiler, an error in a graph), that variant is dropped with
one log line giving the exception, and the others are still measured.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import logging
import os
import shutil
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor

from eventrecon.fields.nerf import NeRFField

log = logging.getLogger("benchmarks.compile")
CONF = str(Path(__file__).resolve().parents[1] / "conf")
FIELD_VARIANTS = ("eager", "bf16", "compiled", "compiled_bf16")
STEP_VARIANTS = ("eager", "bf16", "compiled_field", "compiled_step", "compiled_step_bf16")
#: a step function returns its loss (a float); it does its own forward, backward and update
Step = Callable[[int], float]


def autocast(bf16: bool) -> contextlib.AbstractContextManager:
    """bf16 autocast on the CPU, or nothing."""
    return torch.autocast("cpu", dtype=torch.bfloat16) if bf16 else contextlib.nullcontext()


def dynamo_counts() -> tuple[int, int]:
    """(graphs compiled, graph breaks) so far in this process."""
    from torch._dynamo.utils import counters

    return int(counters["stats"]["unique_graphs"]), int(sum(counters["graph_break"].values()))


def field_steps(arch: dict, batch: int, seed: int, variants: list[str], mode: str | None = None
                ) -> tuple[dict[str, Step], dict[str, str]]:
    """The field-step functions of ``variants`` and their forward accuracy vs eager."""
    gen = torch.Generator().manual_seed(seed)
    xyz, t = torch.rand(batch, 3, generator=gen) * 2 - 1, torch.rand(batch, 1, generator=gen)
    target_s, target_rgb = torch.rand(batch, generator=gen), torch.rand(batch, 3, generator=gen)
    torch.manual_seed(seed)
    base = NeRFField(anneal_steps=0, **arch)
    with torch.no_grad():
        ref_s, ref_rgb = base(xyz, t)
    steps: dict[str, Step] = {}
    accuracy: dict[str, str] = {}
    for name in variants:
        field = copy.deepcopy(base)
        fn = torch.compile(field, mode=mode) if name.startswith("compiled") else field
        opt = torch.optim.AdamW(field.parameters(), lr=1e-4, weight_decay=0.1)
        bf16 = name.endswith("bf16")

        def step(i: int, fn: Callable = fn, opt: torch.optim.Optimizer = opt,
                 bf16: bool = bf16) -> float:
            with autocast(bf16):
                sigma, rgb = fn(xyz, t)
            loss = F.mse_loss(sigma.float(), target_s) + F.mse_loss(rgb.float(), target_rgb)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            return float(loss.detach())

        steps[name] = step
        if not name.startswith("compiled"):  # compiled: measured after its warm-up
            with torch.no_grad(), autocast(bf16):
                s, rgb = fn(xyz, t)
            ds = float((s.float() - ref_s).abs().max()) / float(ref_s.max())
            drgb = float((rgb.float() - ref_rgb).abs().max())
            accuracy[name] = f"max|Δσ|/max σ {ds:.1e}, max|Δrgb| {drgb:.1e}"
    return steps, accuracy


def real_steps(arch: dict, rays: int | None, data_dir: str, variants: list[str],
               mode: str | None = None) -> dict[str, Step]:
    """The whole-step functions of ``variants`` (module docstring, item 2)."""
    from hydra import compose, initialize_config_dir

    from eventrecon.data.batcher import Segment
    from eventrecon.engine import build
    from eventrecon.engine.losses import total_loss
    from eventrecon.engine.module import EventNeRFModule, step_generator

    over = ["model=nerf", "render.skip=none", "model.anneal_steps=0", f"data_dir={data_dir}",
            f"model.depth={arch['depth']}", f"model.width={arch['width']}",
            f"model.skip={arch['skip']}"] + ([f"trainer.n_rays={rays}"] if rays else [])
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(config_name="config", overrides=over)
    ds = build.load_dataset(cfg)
    props = build.scene_properties(cfg, ds)
    base = build.build_module(cfg, props, ds.splits["train"], Segment(0.0, 1000.0))
    n_rays, loss_step = int(cfg.trainer.n_rays), 0
    steps: dict[str, Step] = {}
    for name in variants:
        field = copy.deepcopy(base.field)
        module = EventNeRFModule(field, base.renderer, base.batcher, base.loss_cfg,
                                 base.step_cfg)
        if name == "compiled_field":
            module.field = torch.compile(field, dynamic=True, mode=mode)
        opt = module.configure_optimizers()

        def render_loss(batch: dict, gen: torch.Generator, m: EventNeRFModule = module
                        ) -> Tensor:
            return total_loss(m.render_three(batch, gen), batch, m.loss_cfg, loss_step)["loss"]

        fn = (torch.compile(render_loss, dynamic=True, mode=mode)
              if name.startswith("compiled_step")
              else render_loss)
        bf16 = name.endswith("bf16")

        def step(i: int, fn: Callable = fn, opt: torch.optim.Optimizer = opt,
                 bf16: bool = bf16, module: EventNeRFModule = module) -> float:
            gen = step_generator(0, i)
            batch = module.batcher.sample(n_rays, gen)
            with autocast(bf16):
                loss = fn(batch, gen)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            return float(loss.detach())

        steps[name] = step
    return steps


def measure(label: str, steps: dict[str, Step], warmup: int, reps: int,
            accuracy: dict[str, str] | None = None) -> dict[str, dict]:
    """Warm up each variant (its first step timed apart), then alternate timed steps."""
    accuracy = dict(accuracy or {})
    rows: dict[str, dict] = {}
    first_loss: dict[str, float] = {}
    for name, step in list(steps.items()):
        g0, b0 = dynamo_counts()
        t0 = time.perf_counter()
        try:
            first_loss[name] = step(0)
            first = time.perf_counter() - t0
            for i in range(1, warmup):
                step(i)
        except Exception as e:  # noqa: BLE001 - inductor's errors are of many kinds
            line = (str(e).strip().splitlines() or [""])[0]
            log.info("%s %-18s inductor failed, variant dropped: %s: %s", label, name,
                     type(e).__name__, line)
            steps.pop(name)
            continue
        g1, b1 = dynamo_counts()
        rows[name] = {"first_s": first, "warmup_s": time.perf_counter() - t0,
                      "graphs": g1 - g0, "breaks": b1 - b0, "times": []}
    for i in range(warmup, warmup + reps):
        for name, step in steps.items():
            t0 = time.perf_counter()
            step(i)
            rows[name]["times"].append(time.perf_counter() - t0)
    eager = rows.get("eager")
    for name, r in rows.items():
        r["median_s"] = statistics.median(r["times"])
        r["vs_eager"] = eager["median_s"] / r["median_s"] if eager else float("nan")
        if name not in accuracy and "eager" in first_loss:
            rel = abs(first_loss[name] - first_loss["eager"]) / abs(first_loss["eager"])
            accuracy[name] = f"first loss rel. diff {rel:.1e}"
        log.info("%s %-18s %8.1f ms/step  x%5.2f vs eager  | warm-up %6.1f s (first step "
                 "%6.1f s, %d graphs, %d breaks)  | %s", label, name, r["median_s"] * 1e3,
                 r["vs_eager"], r["warmup_s"], r["first_s"], r["graphs"], r["breaks"],
                 accuracy.get(name, ""))
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks compile",
                                 description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n".join(__doc__.splitlines()[1:]))
    ap.add_argument("--depth", type=int, default=4, help="NeRF layers (trainer=cpu: 4)")
    ap.add_argument("--width", type=int, default=128, help="NeRF width (trainer=cpu: 128)")
    ap.add_argument("--skip", type=int, default=-1, help="skip layer (-1: none; paper: 4)")
    ap.add_argument("--batch", type=int, default=16384, help="samples of the field step")
    ap.add_argument("--rays", type=int, default=None, help="rays of the whole step "
                    "(default: trainer.n_rays, 256)")
    ap.add_argument("--warmup", type=int, default=3, help="steps per variant before timing")
    ap.add_argument("--reps", type=int, default=5, help="timed steps per variant")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--field-variants", nargs="+", choices=FIELD_VARIANTS,
                    default=list(FIELD_VARIANTS))
    ap.add_argument("--step-variants", nargs="+", choices=STEP_VARIANTS,
                    default=list(STEP_VARIANTS))
    ap.add_argument("--no-step", action="store_true", help="skip the whole-step measurement")
    ap.add_argument("--data-dir", default="data")
    ap.add_argument("--mode", default=None, choices=("default", "max-autotune",
                                                     "max-autotune-no-cudagraphs"),
                    help="torch.compile's mode (default: its default)")
    ap.add_argument("--warm-cache", action="store_true",
                    help="use inductor's default on-disk cache (default: an empty one)")
    args = ap.parse_args(argv if argv is not None else [])
    torch.set_num_threads(args.threads)
    cache, before = None, os.environ.get("TORCHINDUCTOR_CACHE_DIR")
    if not args.warm_cache:
        cache = tempfile.mkdtemp(prefix="inductor-")
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = cache
    try:
        run(args)
    finally:
        if cache is not None:
            shutil.rmtree(cache, ignore_errors=True)
            if before is None:
                os.environ.pop("TORCHINDUCTOR_CACHE_DIR", None)
            else:
                os.environ["TORCHINDUCTOR_CACHE_DIR"] = before


def run(args: argparse.Namespace) -> None:
    """Both measurements with the parsed arguments."""
    arch = dict(depth=args.depth, width=args.width, skip=args.skip)
    log.info("NeRF %dx%d (skip %d), %d threads, torch %s, CPU capability %s, compile mode %s, "
             "inductor cache %s", args.depth, args.width, args.skip, args.threads,
             torch.__version__, torch.backends.cpu.get_cpu_capability(),
             args.mode or "default", os.environ.get("TORCHINDUCTOR_CACHE_DIR", "default"))
    steps, acc = field_steps(arch, args.batch, args.seed, args.field_variants, args.mode)
    measure(f"field[{args.batch}]", steps, args.warmup, args.reps, acc)
    if not args.no_step:
        steps = real_steps(arch, args.rays, args.data_dir, args.step_variants, args.mode)
        measure("step", steps, args.warmup, args.reps)


if __name__ == "__main__":
    import sys

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("eventrecon").setLevel(logging.WARNING)
    main(sys.argv[1:])
