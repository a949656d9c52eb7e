"""Training throughput of the NeRF MLP field: samples per second of one full step.

One step = field forward on a batch of (x, y, z, t) samples, an MSE loss on density and
colour, backward, and an AdamW step (lr 1e-4, weight decay 0.1) — the per-sample work
of a training iteration without the compositing. Compared with a naive implementation of
the same network (per-band Python loop for the encoding, out-of-place activations), the
style of common NeRF reimplementations, with the same weights (the largest output
difference of the two is logged), to give a ratio. ``torch.compile`` and bf16 autocast
of this field and of the whole step: ``python -m benchmarks compile``.

Usage::

    python -m benchmarks nerf                  # 8x256, 16384 samples, 2 threads
    python -m benchmarks nerf --depth 4 --width 128 --skip -1 --batch 49152 --threads 1
    python -m benchmarks nerf --renderer       # also rays/s of Renderer + field

Prints one line per implementation (best and median samples/s over the timed steps,
the two implementations alternating step by step) and the ratio of the best.
"""

from __future__ import annotations

import argparse
import logging
import time

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from eventrecon.fields.nerf import NeRFField
from eventrecon.render.volume import VolumeRenderer

log = logging.getLogger("benchmarks.nerf")

class NaiveNeRF(nn.Module):
    """The same network as :class:`NeRFField` written the straightforward way (the
    reference for the ratio): the encoding as a Python loop over bands and functions,
    ``2·ReLU`` out of place, no band-annealing window (``anneal_steps=0``). Parameter names
    are :class:`NeRFField`'s, so ``load_state_dict(ours.state_dict(), strict=False)``
    makes the two compute the same function (checked in :func:`main`)."""

    def __init__(self, depth: int, width: int, skip: int, pos_bands: int, time_bands: int,
                 colour_width: int, remap_width: int = 256) -> None:
        super().__init__()
        self.pos_bands, self.time_bands = pos_bands, time_bands
        self.skip = skip if 0 <= skip < depth - 1 else -1
        in_dim = 3 * (1 + 2 * pos_bands) + (1 + 2 * time_bands)
        layers = [nn.Linear(in_dim, width)]
        for i in range(1, depth):
            layers.append(nn.Linear(width + (in_dim if i - 1 == self.skip else 0), width))
        self.layers = nn.ModuleList(layers)
        self.density = nn.Linear(width, 1)
        self.colour_remap = nn.Linear(width, remap_width)
        self.colour_hidden = nn.Linear(remap_width, colour_width)
        self.colour_out = nn.Linear(colour_width, 3)

    @staticmethod
    def embed(x: Tensor, n_bands: int) -> Tensor:
        out = [x]
        for k in range(n_bands):
            for fn in (torch.sin, torch.cos):
                out.append(fn(x * 2.0**k))
        return torch.cat(out, dim=-1)

    def forward(self, xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        enc = torch.cat([self.embed(xyz, self.pos_bands), self.embed(t, self.time_bands)], -1)
        h = enc
        for i, layer in enumerate(self.layers):
            h = 2.0 * F.relu(layer(h))
            if i == self.skip:
                h = torch.cat([enc, h], dim=-1)
        sigma = F.softplus(self.density(h)[:, 0])
        hidden = 2.0 * F.relu(self.colour_hidden(self.colour_remap(h)))
        return sigma, torch.sigmoid(self.colour_out(hidden))


class _Stepper:
    """One training step (forward, MSE on σ and colour, backward, AdamW) on a fixed batch."""

    def __init__(self, field: nn.Module, batch: int, seed: int) -> None:
        gen = torch.Generator().manual_seed(seed)
        self.field = field
        self.xyz = torch.rand(batch, 3, generator=gen) * 2 - 1
        self.t = torch.rand(batch, 1, generator=gen)
        self.target_sigma = torch.rand(batch, generator=gen)
        self.target_rgb = torch.rand(batch, 3, generator=gen)
        self.opt = torch.optim.AdamW(field.parameters(), lr=1e-4, weight_decay=0.1)

    def __call__(self) -> float:
        t0 = time.perf_counter()
        sigma, rgb = self.field(self.xyz, self.t)
        loss = F.mse_loss(sigma, self.target_sigma) + F.mse_loss(rgb, self.target_rgb)
        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        self.opt.step()
        return time.perf_counter() - t0


def time_interleaved(steppers: dict[str, _Stepper], steps: int, warmup: int
                     ) -> dict[str, list[float]]:
    """Per-step seconds of each stepper, alternating them step by step.

    Alternating makes both see the same background load (the machine may be shared);
    the best step is the least disturbed estimate, the median the typical one.
    """
    times: dict[str, list[float]] = {name: [] for name in steppers}
    for i in range(warmup + steps):
        for name, step in steppers.items():
            sec = step()
            if i >= warmup:
                times[name].append(sec)
    return times


def time_renderer(field: nn.Module, rays: int, n_coarse: int, n_fine: int, steps: int,
                  seed: int) -> float:
    """Median seconds of a renderer training step on ``rays`` rays through the cylinder."""
    gen = torch.Generator().manual_seed(seed)
    renderer = VolumeRenderer(n_coarse, n_fine)
    o = torch.tensor([[-2.0, -0.25, 0.0]]).expand(rays, 3).clone()
    d = torch.nn.functional.normalize(
        torch.tensor([[1.0, 0.0, 0.0]]) + 0.1 * torch.randn(rays, 3, generator=gen), dim=-1)
    t = torch.rand(rays, 1, generator=gen)
    bg = torch.full((rays, 3), 0.5)
    opt = torch.optim.AdamW(field.parameters(), lr=1e-4, weight_decay=0.1)
    times = []
    for i in range(steps + 1):
        t0 = time.perf_counter()
        levels = renderer.render_rays(field, o, d, t, bg, perturb=True, gen=gen)
        loss = sum(((lv["rgb"] - 0.3) ** 2).mean() for lv in levels)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if i > 0:
            times.append(time.perf_counter() - t0)
    return sorted(times)[len(times) // 2]


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(prog="python -m benchmarks nerf",
                                description=__doc__.split("\n")[0])
    p.add_argument("--depth", type=int, default=8)
    p.add_argument("--width", type=int, default=256)
    p.add_argument("--skip", type=int, default=4)
    p.add_argument("--batch", type=int, default=16384, help="samples per step")
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--renderer", action="store_true",
                   help="also time VolumeRenderer(32, 32) + field on 256 rays x 3 times")
    args = p.parse_args(argv if argv is not None else [])
    torch.set_num_threads(args.threads)
    arch = dict(depth=args.depth, width=args.width, skip=args.skip, pos_bands=14,
                time_bands=7, colour_width=128)
    torch.manual_seed(args.seed)
    ours = NeRFField(anneal_steps=0, **arch)
    torch.manual_seed(args.seed)
    naive = NaiveNeRF(**arch)
    naive.load_state_dict(ours.state_dict(), strict=False)  # the same function
    with torch.no_grad():
        probe = torch.rand(256, 3) * 2 - 1, torch.rand(256, 1)
        diff = max(float((a - b).abs().max()) for a, b in zip(ours(*probe), naive(*probe)))
    log.info(f"max |eventrecon - naive| on 256 samples: {diff:.1e} (same weights)")
    times = time_interleaved({"eventrecon": _Stepper(ours, args.batch, args.seed),
                              "naive": _Stepper(naive, args.batch, args.seed)},
                             args.steps, args.warmup)
    best = {}
    for name, ts in times.items():
        best[name] = args.batch / min(ts)
        median = sorted(ts)[len(ts) // 2]
        log.info(f"{name:>10}: best {best[name] / 1e3:7.1f} k samples/s, median "
              f"{args.batch / median / 1e3:7.1f} k samples/s ({median * 1e3:7.1f} ms/step; "
              f"{args.depth}x{args.width}, batch {args.batch}, {args.threads} threads)")
    log.info(f"     ratio (best): {best['eventrecon'] / best['naive']:.2f}x")
    if args.renderer:
        rays = 3 * 256
        sec = time_renderer(ours, rays, 32, 32, args.steps, args.seed)
        log.info(f"  renderer: {rays / sec:8.0f} rays/s  ({sec * 1e3:7.1f} ms/step, 768 rays, "
              f"32 + 32 samples, both levels)")


if __name__ == "__main__":
    import sys

    logging.basicConfig(level=logging.INFO, format="%(message)s")
    main(sys.argv[1:])
