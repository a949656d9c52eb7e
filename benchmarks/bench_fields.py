"""Throughput of one full training step (forward + backward + Adam step) per backbone.

    python benchmarks/bench_fields.py                      # 2 threads, 2^16 samples/step
    python benchmarks/bench_fields.py --threads 1 --compile --out bench.json

For each backbone the same run also times a *naive* version of it (the slow references:
NGP with Python loops over levels and corners, TensoRF-CP / HexPlane sampling their
factors by explicit corner gathers instead of ``grid_sample``) and prints the speed-up.
Sizes: NGP at paper scale (2^19 table), TensoRF-CP and HexPlane at their CPU presets'
final resolution (conf/model/*.yaml), the NeRF MLP at the paper's 8×256 (its naive
version is in ``bench_nerf``). The naive versions run on the same number of samples
(``--naive-n`` to change it). ``ngp_compiled`` also reports its ratio to eager NGP.
Medians over ``--reps`` timed steps.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import statistics
import time
from collections.abc import Callable

import torch
from torch import nn

from baselines import HexPlaneField, NGPField, TensoRFCPField, hash_encode_reference
from baselines.grids import sample_grid_reference

log = logging.getLogger("benchmarks.fields")

def _make_naive(field: nn.Module) -> nn.Module:
    """Swap the vectorised encoder of ``field`` for its slow reference (in place)."""
    if isinstance(field, NGPField):
        enc = field.encoding
        enc.forward = lambda u: hash_encode_reference(enc, u)  # type: ignore[method-assign]
    else:
        grids = field.grids
        grids.forward = lambda c: [  # type: ignore[method-assign]
            sample_grid_reference(f, c[:, list(ax)]) for f, ax in zip(grids.factors, grids.axes)]
    return field


def _backbones(compile_ngp: bool) -> dict[str, tuple[Callable[[], nn.Module], float]]:
    out: dict[str, tuple[Callable[[], nn.Module], float]] = {
        "ngp": (lambda: NGPField(), 1e-3),
        "tensorf_cp": (lambda: TensoRFCPField(n_growth=0), 1e-2),
        "hexplane": (lambda: HexPlaneField(n_growth=0), 1e-2),
    }
    if compile_ngp:
        out["ngp_compiled"] = (lambda: NGPField(compile=True), 1e-3)
    from eventrecon.fields.nerf import NeRFField

    out["nerf"] = (lambda: NeRFField(anneal_steps=0), 1e-4)  # the paper's 8x256
    return out


def time_steps(field: nn.Module, lr: float, n: int, reps: int, warmup: int = 2
               ) -> tuple[float, float]:
    """Median seconds of one training step on ``n`` random samples; also the first step's."""
    opt = torch.optim.Adam(field.param_groups(lr) if hasattr(field, "param_groups")
                           else field.parameters())
    g = torch.Generator().manual_seed(0)
    xyz = torch.rand(n, 3, generator=g) * 2 - 1
    t = torch.rand(n, 1, generator=g)

    def step() -> None:
        sigma, rgb = field(xyz, t)
        loss = sigma.mean() + rgb.mean()
        reg = field.regularization() if hasattr(field, "regularization") else None
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
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=65536, help="samples per training step")
    ap.add_argument("--naive-n", type=int, default=None,
                    help="samples for the naive versions (default: --n)")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--compile", action="store_true", help="also time NGP with torch.compile")
    ap.add_argument("--only", nargs="*", help="subset of backbones")
    ap.add_argument("--out", help="write the results as JSON")
    args = ap.parse_args(argv if argv is not None else [])
    torch.set_num_threads(args.threads)
    rows = []
    for name, (make, lr) in _backbones(args.compile).items():
        if args.only and name not in args.only:
            continue
        sec, first = time_steps(make(), lr, args.n, args.reps)
        row = {"backbone": name, "samples_per_s": args.n / sec, "step_s": sec,
               "first_step_s": first}
        if name in ("ngp", "tensorf_cp", "hexplane"):
            naive_n = args.naive_n or args.n
            nsec, _ = time_steps(_make_naive(make()), lr, naive_n, max(1, args.reps // 2), 1)
            row["naive_samples_per_s"] = naive_n / nsec
            row["speedup"] = row["samples_per_s"] / row["naive_samples_per_s"]
        eager = next((r for r in rows if r["backbone"] == "ngp"), None)
        if name == "ngp_compiled" and eager is not None:
            row["vs_eager"] = row["samples_per_s"] / eager["samples_per_s"]
        rows.append(row)
        log.info(f"{name:14s} {row['samples_per_s'] / 1e3:9.1f} k samples/s  "
                 f"(step {sec * 1e3:7.1f} ms, first {first:6.2f} s)"
                 + (f"  naive {row['naive_samples_per_s'] / 1e3:7.1f} k/s  x{row['speedup']:.1f}"
                    if "speedup" in row else "")
                 + (f"  x{row['vs_eager']:.2f} vs eager" if "vs_eager" in row else ""))
    meta = {"threads": args.threads, "n": args.n, "torch": torch.__version__,
            "loadavg": os.getloadavg()}
    log.info(f"# {meta}")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump({"meta": meta, "rows": rows}, fh, indent=2)


if __name__ == "__main__":
    import sys

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    main(sys.argv[1:])
