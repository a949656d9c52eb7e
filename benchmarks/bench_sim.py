"""Simulator accuracy and throughput: an analytic ground truth, then the library scenes.

1. *grating* — a sliding sinusoidal grating with closed-form crossing times, the
   DAVIS 346×260 side-by-side test: pixel (row ``i``, column ``j``) sees
   ``I = m·(1 + c_j·sin(2π f_i t + φ_j)) + ε``, ``L = log I``, ``f_i`` 2…40 Hz by row,
   ``c_j`` 5…95 % by column (bin centres: no row returns exactly to ``L(0)`` on a frame),
   ``φ_j = 2π(j + ½)/32``, 0.5 s (``m = ½, ε = 0.01``). The true
   events follow the reference-level model exactly (ON at ``r + θ``, ``r ← r + θ``; OFF
   alike): split at the extrema ``2π f t + φ = π/2 + kπ``, each level is crossed once per
   monotone piece, at ``arcsin``. A true crossing whose extremum passes its level by less
   than ``1e-3·θ`` (and the event it pairs with) is *marginal*: missing it is no error.
   Each emitted event is matched to the nearest true one of the same pixel, level and
   polarity (within 2 ms): *missed* true events, *extra* emitted ones, timestamp error.
   Measured: the adaptive core on the analytic signal (spec defaults, sampling
   included), frame-fed emission (:func:`~eventrecon.sim.ideal.frame_events`, 501 log
   frames at 1 kHz) and, with ``--v2e DIR`` (a v2e checkout; not a dependency), v2e's
   ``EventEmulator`` on the same float64 log frames (noise, bandwidth, leak and
   refractory period off), its events/s timed alternately with frame-fed emission;
2. *crossings* / *core* — emission from 400 samples per pixel, and the core, on
   ``4·sin(2π f t + φ)`` (``f`` 3…7, about 150 crossings per pixel);
3. *scene* — ``spheres`` and ``rig_lowlight`` end to end, and the default dataset.

    python -m benchmarks sim [--repeats 3] [--quick] [--only grating|core|scene]
                             [--v2e DIR] [--baseline OLD_IDEAL_PY]
                             [--max-log-step 0.25] [--max-step 2e-3]   (the grating's core)

Medians over repeats, torch and numpy on one thread (run with ``OMP_NUM_THREADS=1``).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import logging
import statistics
import sys
import tempfile
import time
import types
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from eventrecon.sim import event_sim, ideal
from eventrecon.sim.event_sim import simulate_events
from eventrecon.sim.ideal import crossings, frame_events
from eventrecon.sim.pipeline import ensure_dataset, torch_threads
from eventrecon.sim.raytrace import PixelRenderer
from eventrecon.sim.spec import build_cameras, parse_spec

log = logging.getLogger("benchmarks.sim")
CONF = Path(__file__).resolve().parents[1] / "conf" / "scene"


class Grating:
    """The sliding grating (module docstring); times normalised to ``[0, 1]`` = ``T`` s."""

    def __init__(self, width: int = 346, height: int = 260, T: float = 0.5):
        self.W, self.H, self.T, self.m, self.eps = width, height, T, 0.5, 1e-2
        i, j = np.divmod(np.arange(width * height), width)
        self.c = 0.05 + 0.9 * (j + 0.5) / width
        self.a = 2 * np.pi * (2.0 + 38.0 * (i + 0.5) / height) * T        # rad per unit
        self.phi = 2 * np.pi * (j + 0.5) / 32.0
        self.P = width * height

    def __call__(self, g: np.ndarray, t: np.ndarray) -> np.ndarray:
        """``L [N]`` of pixels ``g [N]`` at times ``t [N]``: one buffer, updated in place
        (the same values as the plain expression, about 25 % faster)."""
        x = self.a[g]
        x *= t
        x += self.phi[g]
        np.sin(x, out=x)
        x *= self.c[g]
        x += 1.0
        x *= self.m
        x += self.eps
        return np.log(x, out=x)

    def truth(self, theta: float, tol: float = 1e-3) -> dict:
        """True events ``g, t, p, level`` (index, ``L(0) + level·θ``) and ``optional``."""
        L_of = lambda s, c: np.log(self.m * (1 + c * s) + self.eps)  # noqa: E731
        a, phi, c, P = self.a, self.phi, self.c, self.P
        k0 = np.ceil((phi - np.pi / 2) / np.pi).astype(np.int64)      # first extremum index
        pieces = np.floor((a + phi - np.pi / 2) / np.pi).astype(np.int64) - k0 + 2
        L0, lev = L_of(np.sin(phi), c), np.zeros(P, np.int64)
        out = []
        for q in range(int(pieces.max())):
            sel = np.flatnonzero(pieces > q)
            ps = np.where(q == 0, phi[sel], np.pi / 2 + (k0[sel] + q - 1) * np.pi)
            pe = np.where(q == pieces[sel] - 1, a[sel] + phi[sel],
                          np.pi / 2 + (k0[sel] + q) * np.pi)
            Le, rising = L_of(np.sin(pe), c[sel]), np.cos(0.5 * (ps + pe)) > 0
            x = (Le - L0[sel]) / theta - lev[sel]
            n = np.where(rising, np.floor(x), np.floor(-x)).astype(np.int64).clip(0)
            gg, up = np.repeat(sel, n), np.repeat(rising, n)
            jj = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n) + 1
            li = np.repeat(lev[sel], n) + np.where(up, jj, -jj)
            level = L0[gg] + li * theta
            s = np.arcsin(np.clip(((np.exp(level) - self.eps) / self.m - 1) / c[gg], -1, 1))
            base = np.where(up, s, np.pi - s)                          # branch of the piece
            psi = base + 2 * np.pi * np.ceil((np.repeat(ps, n) - base) / (2 * np.pi) - 1e-9)
            margin = np.where(up, 1, -1) * (np.repeat(Le, n) - level)
            out.append((gg, (psi - phi[gg]) / a[gg], up, li, margin))
            lev[sel] += np.where(rising, n, -n)
        g, t, up, li, margin = (np.concatenate([o[k] for o in out]) for k in range(5))
        o = np.lexsort((t, g))
        g, t, p, li, margin = g[o], t[o], np.where(up[o], 1, -1), li[o], margin[o]
        opt = margin < tol * theta
        pair = np.flatnonzero(opt[:-1] & (g[1:] == g[:-1]) & (li[1:] == li[:-1] - p[:-1]))
        opt[pair + 1] = True                    # the event a marginal one pairs with
        return {"g": g, "t": t, "p": p, "level": li, "optional": opt}


def match_events(g: np.ndarray, t: np.ndarray, p: np.ndarray, truth: dict,
                 window: float) -> dict:
    """Match events to the truth (same pixel, level, polarity; nearest within
    ``window``). Returns ``missed, required, extra, err`` (``err [matched]`` = ``|Δt|``)."""
    o = np.lexsort((t, g))
    cs = np.cumsum(p[o].astype(np.int64))
    start = np.searchsorted(g[o], g[o])
    li = np.empty_like(cs)
    li[o] = cs - np.where(start > 0, cs[np.maximum(start - 1, 0)], 0)

    def key(gg, ll, pp):
        return (gg.astype(np.int64) * 8192 + ll + 4096) * 2 + (pp > 0)
    kt, ke = key(truth["g"], truth["level"], truth["p"]), key(g, li, p)
    o = np.lexsort((truth["t"], kt))
    kt, tt = kt[o], truth["t"][o]
    pos = np.searchsorted(kt * 2.0 + tt, ke * 2.0 + t)
    best, dist = np.full(t.size, -1), np.full(t.size, np.inf)
    for cand in (pos - 1, pos):
        cc = np.clip(cand, 0, kt.size - 1)
        d = np.where((cand >= 0) & (cand < kt.size) & (kt[cc] == ke), np.abs(tt[cc] - t), np.inf)
        better = d < dist
        best[better], dist[better] = cc[better], d[better]
    ok = dist <= window
    idx = np.flatnonzero(ok)
    idx = idx[np.lexsort((dist[idx], best[idx]))]
    ok[idx[1:][best[idx][1:] == best[idx][:-1]]] = False               # one-to-one
    hit = np.zeros(kt.size, bool)
    hit[best[ok]] = True
    opt = truth["optional"][o]
    return {"missed": int((~hit & ~opt).sum()), "required": int((~opt).sum()),
            "extra": int((~ok).sum()), "err": dist[ok]}


def _load_v2e(path: str | None):
    """v2e's ``EventEmulator`` from a checkout at ``path`` (or ``None``). Modules its
    frame path never uses (GUI, video and file outputs) are stubbed when missing."""
    if not path:
        return None
    sys.path.insert(0, path)
    for name in ("cv2", "h5py", "screeninfo", "engineering_notation", "numba", "easygui",
                 "tkinter", "tkinter.filedialog"):
        try:
            importlib.import_module(name)
        except ImportError:
            stub = types.ModuleType(name)
            stub.get_monitors, stub.EngNumber = (lambda: []), (lambda x, *a, **k: x)
            stub.njit = lambda *a, **k: a[0] if a and callable(a[0]) else (lambda f: f)
            stub.filedialog = types.ModuleType("filedialog")
            sys.modules[name] = stub
    logging.getLogger("v2ecore").setLevel(logging.ERROR)
    return importlib.import_module("v2ecore.emulator").EventEmulator


def _v2e_run(Emulator, frames: np.ndarray, times_s: np.ndarray, theta: float, shape) -> tuple:
    emu = Emulator(pos_thres=theta, neg_thres=theta, sigma_thres=0, cutoff_hz=0,
                   leak_rate_hz=0, refractory_period_s=0, shot_noise_rate_hz=0, device="cpu",
                   hdr=True)                       # hdr: the frames are log intensities
    t0 = time.perf_counter()
    ev = [e for k in range(len(times_s))
          if (e := emu.generate_events(frames[k].reshape(shape), times_s[k])) is not None]
    sec = time.perf_counter() - t0
    ev = np.concatenate(ev)
    g = ev[:, 2].astype(np.int64) * shape[1] + ev[:, 1].astype(np.int64)
    return g, ev[:, 0].astype(np.float64), ev[:, 3].astype(np.int8), sec


def _load_baseline(path: str | None):
    """Another version of :mod:`eventrecon.sim.ideal` from a file (e.g. ``git show
    HEAD~1:src/eventrecon/sim/ideal.py > /tmp/ideal_old.py``), or ``None``."""
    if not path:
        return None
    spec = importlib.util.spec_from_file_location("ideal_baseline", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["ideal_baseline"] = mod
    spec.loader.exec_module(mod)
    return mod


class _Timed:
    """A signal that adds up the seconds spent inside it (``sec``) and its samples."""

    def __init__(self, fn):
        self.fn, self.sec, self.n = fn, 0.0, 0

    def __call__(self, g: np.ndarray, t: np.ndarray) -> np.ndarray:
        t0 = time.perf_counter()
        out = self.fn(g, t)
        self.sec += time.perf_counter() - t0
        self.n += t.size
        return out


def _core(mod, signal, P: int, theta: float, max_log_step: float = 0.25,
          max_step: float = 2e-3):
    """Run ``mod.run_core`` on ``signal``: ``(result, seconds, seconds inside the signal)``."""
    setup = mod.SignalSetup(np.full(P, theta), np.full(P, theta), np.full((P, 3), 1 / 3))
    timed = _Timed(signal)
    t0 = time.perf_counter()
    res = mod.run_core(timed, np.arange(P), setup,
                       mod.CoreSettings(theta, max_log_step, max_step, 1e-6))
    return res, time.perf_counter() - t0, timed.sec


def bench_grating(width: int, height: int, theta: float, repeats: int, Emulator=None,
                  baseline=None, max_log_step: float = 0.25, max_step: float = 2e-3) -> None:
    """Missed / extra / timestamp error and events/s of the event core
    (``max_log_step``, ``max_step``: the spec defaults unless given; the time inside the
    signal reported apart), frame-fed emission and (optionally) v2e and a baseline core on
    the grating; logs one line each."""
    core_settings = {"max_log_step": max_log_step, "max_step": max_step}
    gr = Grating(width, height)
    truth = gr.truth(theta)
    tk = np.linspace(0.0, 1.0, 501)
    frames = np.stack([gr(np.arange(gr.P), np.full(gr.P, x)) for x in tk])
    names = ["core"]
    sec: dict = {k: [] for k in (*names, "frames", "v2e", "base")}
    sig: dict = {k: [] for k in names}
    out: dict = {}
    _core(ideal, Grating(8, 6), 48, theta, **core_settings)         # warm-up
    for _ in range(repeats):                       # alternated, medians below
        out["core"], dt, ds = _core(ideal, gr, gr.P, theta, **core_settings)
        sec["core"].append(dt)
        sig["core"].append(ds)
        if baseline is not None:
            base, dt, _ = _core(baseline, gr, gr.P, theta, **core_settings)
            sec["base"].append(dt)
        t0 = time.perf_counter()
        ff = frame_events(frames, tk, theta, theta)
        sec["frames"].append(time.perf_counter() - t0)
        if Emulator is not None:
            v2e = _v2e_run(Emulator, frames, tk * gr.T, theta, (height, width))
            sec["v2e"].append(v2e[3])
    runs = [(name, (out[name].g, out[name].t, out[name].p)) for name in names]
    runs.append(("frames", ff))
    if baseline is not None:
        runs.append(("base", (base.g, base.t, base.p)))
    if Emulator is not None:
        runs.append(("v2e", (v2e[0], v2e[1] / gr.T, v2e[2])))
    log.info("grating %dx%d θ=%.1f (core: max_log_step %g, max_step %g): %d true events "
             "(%d marginal)", width, height, theta, max_log_step, max_step, truth["g"].size,
             int(truth["optional"].sum()))
    for name, (g, t, p) in runs:
        m = match_events(g, t, p, truth, 2e-3 / gr.T)
        err = m["err"] * gr.T * 1e6
        med = statistics.median(sec[name])
        log.info("  %-13s missed %.4f %% (%d), extra %d, |Δt| median %.3f µs p95 %.3f µs; "
                 "%.2f M events/s (%d events, %.2f s)", name,
                 100 * m["missed"] / m["required"], m["missed"], m["extra"], np.median(err),
                 np.percentile(err, 95), g.size / med / 1e6, g.size, med)
    for name in names:
        core, ds = out[name], statistics.median(sig[name])
        rest = statistics.median(a - b for a, b in zip(sec[name], sig[name]))
        log.info("  %s: %.2f samples/event (%d turn refinements), %d iterations; inside "
                 "the signal %.2f s (%.1f ns/sample), the core's own work %.2f s "
                 "(%.1f ns/sample)", name, core.n_samples / max(core.t.size, 1),
                 core.extra["turn_samples"], core.iterations, ds,
                 1e9 * ds / core.n_samples, rest, 1e9 * rest / core.n_samples)
    if Emulator is not None:
        ratio = statistics.median(v / f for v, f in zip(sec["v2e"], sec["frames"]))
        log.info("  frame-fed / v2e events/s: %.2f (same frames, alternated)", ratio)
    if baseline is not None:
        ratio = statistics.median(b / c for b, c in zip(sec["base"], sec[names[0]]))
        log.info("  core / baseline core speed: %.2f (alternated)", ratio)


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


def bench_core(width: int, height: int, max_log_step: float, baseline=None) -> dict:
    """The core on an analytic signal (no rendering): 4·sin(2π f t + φ) per pixel; with
    a ``baseline`` module, that one's core too (``base_sec``)."""
    P = width * height
    res, sec, _ = _core(ideal, _signal(P), P, 0.5, max_log_step)
    out = {"events": res.t.size, "sec": sec, "samples": res.n_samples}
    if baseline is not None:
        base, out["base_sec"], _ = _core(baseline, _signal(P), P, 0.5, max_log_step)
        out["base_events"] = base.t.size
    return out


def bench_scene(name: str, width: int, height: int, baseline=None) -> dict:
    """Events of the training views of a library scene (rendering included); with a
    ``baseline`` module, simulated by that one's core."""
    cfg = OmegaConf.load(CONF / f"{name}.yaml")
    cfg.width, cfg.height = width, height
    spec = parse_spec(cfg)
    cams, _ = build_cameras(spec)
    pr = PixelRenderer(spec.scene, cams, spec.supersample)
    own = event_sim.run_core
    event_sim.run_core = ideal.run_core if baseline is None else baseline.run_core
    try:
        t0 = time.perf_counter()
        streams, core = simulate_events(spec, pr)
        sec = time.perf_counter() - t0
    finally:
        event_sim.run_core = own
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
    ap.add_argument("--only", choices=["grating", "core", "scene"], help="one part only")
    ap.add_argument("--v2e", metavar="DIR", help="a v2e checkout: also time its emulator")
    ap.add_argument("--baseline", metavar="FILE",
                    help="another ideal.py (e.g. the previous commit's): compare its core")
    ap.add_argument("--max-log-step", type=float, default=0.25,
                    help="the core's step bound in L, in units of θ, on the grating")
    ap.add_argument("--max-step", type=float, default=2e-3,
                    help="the core's longest step on the grating (normalised time)")
    args = ap.parse_args(argv if argv is not None else [])
    sizes = [(96, 72)] + ([] if args.quick else [(346, 260)])
    with torch_threads(1):
        if args.only in (None, "grating"):
            Emulator, baseline = _load_v2e(args.v2e), _load_baseline(args.baseline)
            w, h = sizes[-1]
            for theta in (0.5, 0.2):
                bench_grating(w, h, theta, args.repeats, Emulator, baseline,
                              args.max_log_step, args.max_step)
        for w, h in sizes if args.only in (None, "core") else []:
            m = _median([bench_crossings(w, h) for _ in range(args.repeats)])
            log.info("crossings %dx%d: %.1f M events/s (%d events from %d samples, %.3f s)",
                     w, h, m["events"] / m["sec"] / 1e6, m["events"], m["samples"], m["sec"])
            for mls in (0.25, 1.0):
                runs = [bench_core(w, h, mls, _load_baseline(args.baseline))
                        for _ in range(args.repeats)]
                m = _median(runs)
                log.info("core %dx%d max_log_step=%.2f: %.2f M events/s (%d events, %.2f s, "
                         "%.1f ns/sample)", w, h, mls, m["events"] / m["sec"] / 1e6,
                         m["events"], m["sec"], 1e9 * m["sec"] / m["samples"])
                if args.baseline:
                    log.info("  baseline: %.2f M events/s; speed-up %.2f (alternated)",
                             m["base_events"] / m["base_sec"] / 1e6,
                             statistics.median(r["base_sec"] / r["sec"] for r in runs))
        for w, h in sizes if args.only in (None, "scene") else []:
            for scene in ("spheres", "rig_lowlight"):
                reps = args.repeats if w * h < 20000 else max(1, args.repeats // 2)
                runs, base = [], []
                for _ in range(reps):                  # alternated with the baseline
                    runs.append(bench_scene(scene, w, h))
                    if args.baseline:
                        base.append(bench_scene(scene, w, h, _load_baseline(args.baseline)))
                for tag, rr in (("", runs), (" (baseline core)", base)):
                    if not rr:
                        continue
                    m = _median(rr)
                    log.info("%s %dx%d%s: %d events (%d ideal) in %.2f s = %.3f M events/s; "
                             "%d pixel samples, %.2f µs/pixel sample, %.1f ms per full-view "
                             "sample", scene, w, h, tag, m["events"], m["ideal"], m["sec"],
                             m["events"] / m["sec"] / 1e6, m["samples"], m["us_per_sample"],
                             m["ms_per_frame_equiv"])
    if args.only not in (None, "scene"):
        return
    gen = []
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            ensure_dataset(OmegaConf.load(CONF / "spheres.yaml"), tmp)
            gen.append(time.perf_counter() - t0)
    log.info("generate default scene (spheres, simulate + write): median %.1f s of %s",
             statistics.median(gen), [round(g, 1) for g in gen])


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("eventrecon").setLevel(logging.WARNING)
    main(sys.argv[1:])
