"""What event decay does to the window sums the losses see, measured on a dataset.

``L_event`` and ``L_acc`` compare rendered log changes with ``θ·E(t0, t1)``, where
``E(t0, t1) = V(t1) − V(t0)`` and ``V`` is the decayed running sum of a pixel's
polarities (:mod:`eventrecon.events.accumulate`). On a pixel whose brightness does not
change, the *background*, ``E`` is noise alone: its mean is the drift and its RMS the
error that decay is meant to bound (supplementary Sec. 15; the closed form for Poisson
noise is :func:`eventrecon.events.noise_theory.window_noise_moments`). On the *subject*
(the simulator's masks, or the ``mask/`` folder of the published layout), ``E`` is mostly
signal, and whatever decay changes there changes the training targets.

This module draws training windows exactly as the batcher does
(:func:`eventrecon.data.sampling.sample_window` inside a segment), evaluates ``E`` on every
pixel with ``b = 1`` and with the scene's decay, and reports per region the mean, the RMS
and the RMS of the change decay makes::

    python -m eventrecon.data.window_stats data/rig_noisy-171c56ba9b --segment 90 210
"""

from __future__ import annotations

import argparse
import logging
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from eventrecon import TIME_SPAN
from eventrecon.common.errors import InputError
from eventrecon.data.layout import read_split
from eventrecon.data.sampling import sample_window
from eventrecon.data.types import SplitData
from eventrecon.events.accumulate import DecayedEvents

__all__ = ["RegionStats", "WindowStats", "window_stats", "main"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RegionStats:
    """Window sums ``E`` (in events) over the pixels of one region and every window."""

    pixels: int            # pixel-windows pooled
    mean_plain: float      # mean E without decay (b = 1)
    rms_plain: float       # sqrt(mean E²) without decay
    mean_decayed: float    # the same with the decay
    rms_decayed: float
    rms_change: float      # sqrt(mean (E_b − E_1)²): what decay changes


@dataclass(frozen=True)
class WindowStats:
    """:func:`window_stats`' result: the two regions and the windows they were drawn on."""

    decay: float
    windows: int
    mean_window: float     # mean t1 − t0, time units
    background: RegionStats
    subject: RegionStats | None   # None without masks


class _Sums:
    """Running sums of one region's window sums (constant memory at any sensor size)."""

    def __init__(self) -> None:
        self.n = 0
        self.s = np.zeros(5)   # Σ E₁, Σ E₁², Σ E_b, Σ E_b², Σ (E_b − E₁)²

    def add(self, e1: np.ndarray, eb: np.ndarray) -> None:
        self.n += e1.size
        self.s += [e1.sum(), (e1 * e1).sum(), eb.sum(), (eb * eb).sum(), ((eb - e1) ** 2).sum()]

    def stats(self) -> RegionStats:
        if self.n == 0:
            nan = float("nan")
            return RegionStats(0, nan, nan, nan, nan, nan)
        m = self.s / self.n
        return RegionStats(self.n, float(m[0]), float(np.sqrt(m[1])), float(m[2]),
                           float(np.sqrt(m[3])), float(np.sqrt(m[4])))


def window_stats(split: SplitData, segment: tuple[float, float], decay: float,
                 windows: int = 300, seed: int = 0) -> WindowStats:
    """Window sums with and without decay over ``windows`` training windows of ``segment``.

    Each window is ``(t0, t1)`` of :func:`~eventrecon.data.sampling.sample_window`, mapped
    to ``segment``; ``V`` accumulates from the start of the recording, as in training. A
    pixel is *subject* where the mask of the frame nearest ``t1`` is set. Every pixel of
    every view counts once per window (``[V·H·W]`` values per window and region split).

    Args:
        split: a split with events (``SplitData.events``), masks ``[F, V, H, W]`` optional.
        segment: ``(start, end)`` in time units.
        decay: the decay ``b`` to compare with ``b = 1``.
        windows: how many windows to draw.
        seed: the window generator's seed.

    Raises:
        InputError: without events, with an empty segment or no windows.
    """
    if not split.events:
        raise InputError(split.root, "events/", "a split with events", "none")
    start, end = float(segment[0]), float(segment[1])
    if not end > start:
        raise InputError(split.root, "segment", "start < end", f"[{start}, {end}]")
    if windows < 1:
        raise InputError(split.root, "windows", "at least one window", windows)
    h, w = split.cameras.height, split.cameras.width
    acc = {b: DecayedEvents.from_streams(split.events, h, w, b) for b in (1.0, float(decay))}
    gen = torch.Generator().manual_seed(seed)
    masks = split.masks
    background, subject, length = _Sums(), _Sums(), 0.0
    for _ in range(windows):
        a, c = sample_window(gen)
        t0, t1 = start + a * (end - start), start + c * (end - start)
        length += t1 - t0
        e1 = acc[1.0].window_all(t0, t1).reshape(-1).numpy()
        eb = acc[float(decay)].window_all(t0, t1).reshape(-1).numpy()
        if masks is None:
            background.add(e1, eb)
            continue
        m = masks[int(np.argmin(np.abs(split.frame_times - t1)))].reshape(-1)
        background.add(e1[~m], eb[~m])
        subject.add(e1[m], eb[m])
    return WindowStats(float(decay), windows, length / windows, background.stats(),
                       subject.stats() if masks is not None else None)


def _table(stats: WindowStats) -> str:
    head = (f"| region | pixel-windows | mean E, b=1 | RMS E, b=1 | mean E, b={stats.decay:g} "
            f"| RMS E, b={stats.decay:g} | RMS change |\n|---|---|---|---|---|---|---|")
    rows = [head]
    for name, r in (("background", stats.background), ("subject", stats.subject)):
        if r is not None:
            rows.append(f"| {name} | {r.pixels} | {r.mean_plain:+.3f} | {r.rms_plain:.3f} | "
                        f"{r.mean_decayed:+.3f} | {r.rms_decayed:.3f} | {r.rms_change:.3f} |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    """CLI: print the table for a dataset folder (``<scene>/train`` is read)."""
    ap = argparse.ArgumentParser(prog="python -m eventrecon.data.window_stats",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", type=Path, help="a dataset folder holding train/")
    ap.add_argument("--segment", type=float, nargs=2, metavar=("START", "END"),
                    help="time units (default: the whole recording)")
    ap.add_argument("--decay", type=float, default=0.93, help="b to compare with 1 (0.93)")
    ap.add_argument("--windows", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        split = read_split(args.dataset / "train")
        stats = window_stats(split, tuple(args.segment or (0.0, TIME_SPAN)), args.decay,
                             args.windows, args.seed)
    except InputError as e:
        log.error("%s", e)
        return 2
    log.info("%s: %d windows of mean length %.1f time units\n%s", args.dataset,
             stats.windows, stats.mean_window, _table(stats))
    return 0


if __name__ == "__main__":
    sys.exit(main())
