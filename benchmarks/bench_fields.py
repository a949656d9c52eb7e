"""Throughput of one bare field step (forward + backward + AdamW step) per backbone.

    python -m benchmarks fields                            # trainer=cpu sizes, 2 threads
    python -m benchmarks fields --sizing paper --threads 1 --out bench.json
    python -m benchmarks fields --only ngp ngp_torch       # the hash grid's kernel against torch

Each backbone is built from its config exactly as a run builds it (``conf/model/*.yaml``
with ``--sizing cpu``: the ``trainer=cpu`` sizes of ``conf/sizing/cpu_<model>.yaml``;
``--sizing paper``: the configs' own, the authors' sizes), TensoRF-CP at its final
resolution (``model.n_stages=1``). Samples are uniform in the default clipping
cylinder's bounding box (the field's scene box, as in a run) and times uniform in
``[0, 1]``; the loss is ``mean σ + mean rgb`` plus the field's regulariser.

For the grid backbones the same run also times a *naive* version of the same field
(the slow references: NGP with Python loops over levels and corners,
:func:`baselines.ngp.hash_encode_reference`; TensoRF-CP / HexPlane sampling each factor
by explicit corner gathers, :func:`baselines.grids.sample_grid_reference`, with the
factor's own ``align_corners`` and padding) and logs the speed-up and the largest
difference of the two forward outputs (a check that the reference is the same
function). The naive versions run on ``--naive-n`` samples (default ``--n``).

Each grid backbone runs twice: with its config's ``implementation`` (``auto``: the
compiled CPU kernel of :mod:`eventrecon.kernels` where it applies) and as
``<backbone>_torch`` (``model.implementation=torch``: the PyTorch reference), which also
reports ``auto_vs_torch``, the default's samples per second over the reference's (the
kernel's gain on this flow). Medians over ``--reps`` timed steps after 2 warm-up steps;
the first step is reported separately (it includes compilation, or loading the kernels'
cache).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import statistics
import time
from pathlib import Path

import torch
from hydra import compose, initialize_config_dir
from torch import Tensor

from baselines import NGPField, hash_encode_reference
from baselines.factorised import FactorisedField
from baselines.grids import sample_grid_reference
from eventrecon.engine import build
from eventrecon.engine.module import adamw_fused
from eventrecon.fields.base import Field
from eventrecon.render.clipping import Cylinder

log = logging.getLogger("benchmarks.fields")
CONF = str(Path(__file__).resolve().parents[1] / "conf")

#: name -> config overrides of the backbone.
BACKBONES: dict[str, list[str]] = {
    "ngp": ["model=ngp"],
    "ngp_torch": ["model=ngp", "model.implementation=torch"],
    "tensorf_cp": ["model=tensorf_cp", "model.n_stages=1"],
    "tensorf_cp_torch": ["model=tensorf_cp", "model.n_stages=1", "model.implementation=torch"],
    "hexplane": ["model=hexplane"],
    "hexplane_torch": ["model=hexplane", "model.implementation=torch"],
    "nerf": ["model=nerf", "model.anneal_steps=0"],
}
NAIVE = ("ngp", "tensorf_cp", "hexplane")
#: Suffix of a backbone's PyTorch-reference variant (``model.implementation=torch``).
TORCH = "_torch"


def build_backbone(overrides: list[str], sizing: str) -> tuple[Field, float]:
    """The field of ``overrides`` (``sizing``: ``cpu`` or ``paper``) with its config's lr,
    its scene box set to the default clipping cylinder's."""
    trainer = "trainer=paper" if sizing == "paper" else "trainer=cpu"
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(config_name="config", overrides=[trainer, *overrides])
    field = build.build_field(cfg.model)
    field.set_scene_box(*Cylinder().box())
    return field, float((cfg.model.get("optim") or {}).get("lr", 1e-3))


def make_naive(field: Field) -> Field:
    """Swap the vectorised encoder of ``field`` for its slow reference (in place)."""
    if isinstance(field, NGPField):
        enc = field.encoding
        enc.forward = lambda u: hash_encode_reference(enc, u)  # type: ignore[method-assign]
    elif isinstance(field, FactorisedField):
        grids = field.grids
        grids.forward = lambda c, k=None: [  # type: ignore[method-assign]   # [N, C] each
            sample_grid_reference(f, c[:, list(ax)], ac, grids.padding).t()
            for f, ax, ac in zip(grids.leading(k), grids.axes, grids.align_corners)]
        field.implementation = "torch"   # factor by factor: the sampling above, not a kernel
    else:
        raise TypeError(f"no naive version of {type(field).__name__}")
    return field


def random_samples(n: int, seed: int = 0) -> tuple[Tensor, Tensor]:
    """``n`` points uniform in the default cylinder's box and times uniform in [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = (torch.tensor(v, dtype=torch.float32) for v in Cylinder().box())
    return lo + torch.rand(n, 3, generator=g) * (hi - lo), torch.rand(n, 1, generator=g)


@torch.no_grad()
def max_difference(a: Field, b: Field, n: int = 2048) -> float:
    """Largest absolute difference of the ``(σ, rgb)`` outputs of two fields."""
    xyz, t = random_samples(n, seed=1)
    (sa, ra), (sb, rb) = a(xyz, t), b(xyz, t)
    return max(float((sa - sb).abs().max()), float((ra - rb).abs().max()))


def time_steps(field: Field, lr: float, n: int, reps: int, warmup: int = 2
               ) -> tuple[float, float]:
    """Median seconds of one training step on ``n`` random samples; also the first step's."""
    groups = field.param_groups(lr)
    opt = torch.optim.AdamW(groups, lr=lr, fused=adamw_fused(groups))   # as training's
    xyz, t = random_samples(n)

    def step() -> None:
        sigma, rgb = field(xyz, t)
        loss = sigma.mean() + rgb.mean()
        reg = field.regularization()
        if reg is not None:
            loss = loss + reg
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    t0 = time.perf_counter()
    step()
    first = time.perf_counter() - t0
    for _ in range(warmup - 1):
        step()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        step()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), first


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks fields",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=65536, help="samples per training step")
    ap.add_argument("--naive-n", type=int, default=None,
                    help="samples for the naive versions (default: --n)")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--sizing", choices=("cpu", "paper"), default="cpu",
                    help="cpu: the trainer=cpu sizes; paper: the configs' own (authors')")
    ap.add_argument("--only", nargs="*", choices=list(BACKBONES), help="subset of backbones")
    ap.add_argument("--out", help="write the results as JSON")
    args = ap.parse_args(argv if argv is not None else [])
    torch.set_num_threads(args.threads)
    rows: list[dict] = []
    for name, over in BACKBONES.items():
        if args.only and name not in args.only:
            continue
        field, lr = build_backbone(over, args.sizing)
        sec, first = time_steps(field, lr, args.n, args.reps)
        row = {"backbone": name, "samples_per_s": args.n / sec, "step_s": sec,
               "first_step_s": first, "params": sum(p.numel() for p in field.parameters())}
        if name in NAIVE:
            naive_n = args.naive_n or args.n
            naive = make_naive(build_backbone(over, args.sizing)[0])
            row["naive_max_diff"] = max_difference(build_backbone(over, args.sizing)[0], naive)
            nsec, _ = time_steps(naive, lr, naive_n, max(1, args.reps // 2), 1)
            row["naive_samples_per_s"] = naive_n / nsec
            row["speedup"] = row["samples_per_s"] / row["naive_samples_per_s"]
        auto = next((r for r in rows if name.endswith(TORCH)
                     and r["backbone"] == name[:-len(TORCH)]), None)
        if auto is not None:
            row["auto_vs_torch"] = auto["samples_per_s"] / row["samples_per_s"]
        rows.append(row)
        log.info(f"{name:16s} {row['samples_per_s'] / 1e3:9.1f} k samples/s  "
                 f"(step {sec * 1e3:7.1f} ms, first {first:6.2f} s, "
                 f"{row['params'] / 1e6:.2f} M params)"
                 + (f"  naive {row['naive_samples_per_s'] / 1e3:7.1f} k/s  x{row['speedup']:.1f}"
                    f"  (max |fast - naive| {row['naive_max_diff']:.1e})"
                    if "speedup" in row else "")
                 + (f"  auto x{row['auto_vs_torch']:.2f} vs torch"
                    if "auto_vs_torch" in row else ""))
    meta = {"threads": args.threads, "n": args.n, "sizing": args.sizing,
            "torch": torch.__version__, "loadavg": os.getloadavg()}
    log.info(f"# {meta}")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump({"meta": meta, "rows": rows}, fh, indent=2)


if __name__ == "__main__":
    import sys

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    main(sys.argv[1:])
