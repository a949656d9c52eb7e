"""Simulator throughput at the default size and DAVIS 346×260, three levels deep:

1. *crossings* — the ideal core's event emission from sampled log signals (every
   threshold crossing of each pixel's piecewise-linear signal, its own interpolated
   float64 time), fed 400 samples per pixel of an analytic signal: what a frame-based
   simulator measures;
2. *core* — the adaptive core (:func:`~eventrecon.sim.ideal.run_core`) on an analytic
   signal: step control and crossing emission, no rendering;
3. *scene* — ``spheres`` and ``rig_lowlight`` end to end (ray-traced rendering of every
   sample + effects), and the time to generate the default dataset.

    python -m benchmarks sim [--repeats 3] [--quick]

Figures are medians over repeats, with torch on one CPU thread (what the pipeline uses).
"""

from __future__ import annotations

import argparse
import logging
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from eventrecon.sim.event_sim import simulate_events
from eventrecon.sim.ideal import CoreSettings, SignalSetup, crossings, run_core
from eventrecon.sim.pipeline import ensure_dataset, torch_threads
from eventrecon.sim.raytrace import PixelRenderer
from eventrecon.sim.spec import build_cameras, parse_spec

log = logging.getLogger("benchmarks.sim")
CONF = Path(__file__).resolve().parents[1] / "conf" / "scene"


def _signal(P: int):
    """``4·sin(2π f t + φ)`` per pixel, ``f`` in 3..7: about 150 crossings per pixel."""
    f = 3.0 + np.arange(P) % 5
    phase = np.arange(P) * 0.37
    return lambda g, t: 4.0 * np.sin(2 * np.pi * f[g] * t + phase[g])


def bench_crossings(width: int, height: int, n_samples: int = 400) -> dict:
    """Crossing emission from ``n_samples`` samples per pixel on a shared time grid."""
    P = width * height
    g, sig = np.arange(P), _signal(width * height)
    t = np.linspace(0.0, 1.0, n_samples)
    L = [sig(g, np.full(P, tk)) for tk in t]
    ref, on, off = L[0].copy(), np.full(P, 0.5), np.full(P, 0.5)
    n, t0 = 0, time.perf_counter()
    for k in range(n_samples - 1):
        ev, ref, on, off = crossings(g, np.full(P, t[k]), np.full(P, t[k + 1]), L[k], L[k + 1],
                                     ref, on, off)
        n += sum(e[0].size for e in ev)
    return {"events": n, "sec": time.perf_counter() - t0, "samples": P * n_samples}


def bench_core(width: int, height: int, max_log_step: float) -> dict:
    """The core on an analytic signal (no rendering): 4·sin(2π f t + φ) per pixel."""
    P = width * height
    sig = _signal(P)
    setup = SignalSetup(np.full(P, 0.5), np.full(P, 0.5), np.full((P, 3), 1 / 3))
    t0 = time.perf_counter()
    res = run_core(sig, np.arange(P), setup, CoreSettings(0.5, max_log_step, 2e-3, 1e-6))
    sec = time.perf_counter() - t0
    return {"events": res.t.size, "sec": sec, "samples": res.n_samples}


def bench_scene(name: str, width: int, height: int) -> dict:
    """Events of the training views of a library scene (rendering included)."""
    cfg = OmegaConf.load(CONF / f"{name}.yaml")
    cfg.width, cfg.height = width, height
    spec = parse_spec(cfg)
    cams, _ = build_cameras(spec)
    pr = PixelRenderer(spec.scene, cams, spec.supersample)
    t0 = time.perf_counter()
    streams, core = simulate_events(spec, pr)
    sec = time.perf_counter() - t0
    frames_equiv = core.n_samples / (width * height)
    return {"events": sum(len(s) for s in streams), "ideal": core.t.size, "sec": sec,
            "samples": core.n_samples, "us_per_sample": 1e6 * sec / max(core.n_samples, 1),
            "ms_per_frame_equiv": 1e3 * sec / max(frames_equiv, 1e-9)}


def _median(runs: list[dict]) -> dict:
    return {k: statistics.median(r[k] for r in runs) for k in runs[0]}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m benchmarks sim",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="skip the 346×260 runs")
    args = ap.parse_args(argv if argv is not None else [])
    sizes = [(96, 72)] + ([] if args.quick else [(346, 260)])
    with torch_threads(1):
        for w, h in sizes:
            m = _median([bench_crossings(w, h) for _ in range(args.repeats)])
            log.info("crossings %dx%d: %.1f M events/s (%d events from %d samples, %.3f s)",
                     w, h, m["events"] / m["sec"] / 1e6, m["events"], m["samples"], m["sec"])
            for mls in (0.25, 1.0):
                m = _median([bench_core(w, h, mls) for _ in range(args.repeats)])
                log.info("core %dx%d max_log_step=%.2f: %.2f M events/s (%d events, %.2f s, "
                         "%.1f ns/sample)", w, h, mls, m["events"] / m["sec"] / 1e6,
                         m["events"], m["sec"], 1e9 * m["sec"] / m["samples"])
            for scene in ("spheres", "rig_lowlight"):
                reps = args.repeats if w * h < 20000 else max(1, args.repeats // 2)
                m = _median([bench_scene(scene, w, h) for _ in range(reps)])
                log.info("%s %dx%d: %d events (%d ideal) in %.2f s = %.3f M events/s; "
                         "%d pixel samples, %.2f µs/pixel sample, %.1f ms per full-view sample",
                         scene, w, h, m["events"], m["ideal"], m["sec"],
                         m["events"] / m["sec"] / 1e6, m["samples"], m["us_per_sample"],
                         m["ms_per_frame_equiv"])
    gen = []
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            ensure_dataset(OmegaConf.load(CONF / "spheres.yaml"), tmp)
            gen.append(time.perf_counter() - t0)
    log.info("generate default scene (spheres, simulate + write): median %.1f s of %s",
             statistics.median(gen), [round(g, 1) for g in gen])


if __name__ == "__main__":
    import sys
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("eventrecon").setLevel(logging.WARNING)
    main(sys.argv[1:])
