"""Event-side sensor effects, one small class each, registered by name.

Signal-stage effects configure the event core (:mod:`eventrecon.sim.ideal`) before any
crossing is detected; stream-stage effects then transform each view's event arrays, in
the order the scene lists them. Rates are in Hz and periods in seconds of the scene's
``duration_s`` (time unit ``u = 1000 / duration_s`` per second), never per rendered
sample, so refining the renderer's sampling does not change them.

========================= ======= ========================================================
name (parameters)         stage   what it does
========================= ======= ========================================================
bayer                     signal  RGGB colour pixels: the pixel sees only its channel (R at
                                  even row/even col, B at odd/odd, G elsewhere); without it
                                  the pixel sees the grey level ``(R + G + B) / 3``
bandwidth (cutoff_hz,     signal  first-order low-pass of the log signal before detection,
min_intensity)                    ``τ dL_f/dt = L − L_f``, ``τ = 1/(2π f_c)``,
                                  ``f_c = cutoff_hz·max(I, min_intensity)`` (dim = slow)
threshold_mismatch        signal  frozen per-pixel ``θ_on, θ_off ~ N(θ, σ²)``
(sigma)
threshold_noise (sigma)   signal  after each event the pixel's threshold is re-drawn as
                                  ``θ_pixel + N(0, σ²)``
shot_noise (rate_hz,      stream  Poisson noise events, ``rate_hz`` per pixel, uniform time,
on_fraction)                      ON with probability ``on_fraction``
leak (rate_hz)            stream  ON events of each pixel every ``1/rate_hz`` s, random phase
refractory (period_s)     stream  drops every event closer than ``period_s`` to the last
                                  kept event of its pixel
timestamp_jitter          stream  ``t ← t + N(0, sigma_s²)`` (clipped to the span, re-sorted)
(sigma_s)
hot_pixels (fraction,     stream  a random ``fraction`` of pixels fires Poisson ON events at
rate_hz)                          ``rate_hz``
========================= ======= ========================================================

Thresholds are clipped below at ``0.01·θ`` (a non-positive threshold has no meaning).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from eventrecon import TIME_SPAN
from eventrecon.sim.ideal import SignalSetup
from eventrecon.sim.registry import Effect, Param, Registry, non_negative, positive

__all__ = ["EVENT_EFFECTS", "EventContext", "ViewEvents", "bayer_channel", "merge_events",
           "first_order_lowpass"]

EVENT_EFFECTS = Registry("events")


class ViewEvents(NamedTuple):
    """Events of one view: ``pix [E]`` int64 (``row·W + col``), ``t [E]`` float64 time
    units, ``p [E]`` int8, sorted by ``t``."""

    pix: np.ndarray
    t: np.ndarray
    p: np.ndarray


@dataclass
class EventContext:
    """Sensor geometry and scene constants the effects need."""

    width: int
    height: int
    n_views: int
    tonemap_eps: float
    threshold: float
    duration_s: float

    @property
    def n_pixels(self) -> int:
        return self.width * self.height

    @property
    def units_per_s(self) -> float:
        return TIME_SPAN / self.duration_s


def bayer_channel(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """RGGB channel index (0 R, 1 G, 2 B) of pixels: ``(row mod 2) + (col mod 2)``."""
    return (np.asarray(rows) % 2) + (np.asarray(cols) % 2)


def merge_events(*parts: ViewEvents) -> ViewEvents:
    """Concatenate event sets and sort by ``(t, pix)``."""
    pix = np.concatenate([a.pix for a in parts])
    t = np.concatenate([a.t for a in parts])
    p = np.concatenate([a.p for a in parts])
    order = np.lexsort((pix, t))
    return ViewEvents(pix[order], t[order], p[order])


def first_order_lowpass(y_a: np.ndarray, u_a: np.ndarray, u_b: np.ndarray,
                        tau: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """Exact step of ``τ y' = u − y`` over ``dt`` with ``u`` linear from ``u_a`` to ``u_b``.

    ``y_b = u_b − (u_b − u_a)·(τ/dt)(1 − e^{−dt/τ}) + (y_a − u_a)·e^{−dt/τ}``
    (first-order hold, so the result does not depend on how finely ``u`` is sampled
    while it is linear).
    """
    x = dt / tau
    e = np.exp(-x)
    g = np.where(x > 1e-8, -np.expm1(-x) / np.maximum(x, 1e-300), 1.0 - 0.5 * x)
    return u_b - (u_b - u_a) * g + (y_a - u_a) * e


# --------------------------------------------------------------------- signal stage

@EVENT_EFFECTS.register
class Bayer(Effect):
    name = "bayer"
    stage = "signal"

    def configure(self, setup: SignalSetup, ctx: EventContext, rng: np.random.Generator) -> None:
        g = np.arange(setup.channel_weights.shape[0])
        rc = g % ctx.n_pixels
        ch = bayer_channel(rc // ctx.width, rc % ctx.width)
        setup.channel_weights = np.eye(3)[ch]


@EVENT_EFFECTS.register
class Bandwidth(Effect):
    name = "bandwidth"
    stage = "signal"
    PARAMS = {"cutoff_hz": Param(float, check=positive, expect="a frequency > 0 Hz"),
              "min_intensity": Param(float, 1e-2, positive, "an intensity > 0")}

    def configure(self, setup: SignalSetup, ctx: EventContext, rng: np.random.Generator) -> None:
        eps, fc, floor, dur = ctx.tonemap_eps, self.p["cutoff_hz"], self.p["min_intensity"], \
            ctx.duration_s

        def lowpass(y_a, u_a, u_b, dt):
            intensity = 0.5 * (np.exp(u_a) + np.exp(u_b)) - eps
            tau = 1.0 / (2 * np.pi * fc * np.maximum(intensity, floor))
            return first_order_lowpass(y_a, u_a, u_b, tau, dt * dur)

        setup.lowpass = lowpass


@EVENT_EFFECTS.register
class ThresholdMismatch(Effect):
    name = "threshold_mismatch"
    stage = "signal"
    PARAMS = {"sigma": Param(float, check=non_negative, expect="a std ≥ 0 (log units)")}

    def configure(self, setup: SignalSetup, ctx: EventContext, rng: np.random.Generator) -> None:
        n = setup.theta_on.shape[0]
        lo = 0.01 * ctx.threshold
        setup.theta_on = np.maximum(setup.theta_on + self.p["sigma"] * rng.standard_normal(n), lo)
        setup.theta_off = np.maximum(setup.theta_off + self.p["sigma"] * rng.standard_normal(n),
                                     lo)


@EVENT_EFFECTS.register
class ThresholdNoise(Effect):
    name = "threshold_noise"
    stage = "signal"
    PARAMS = {"sigma": Param(float, check=non_negative, expect="a std ≥ 0 (log units)")}

    def configure(self, setup: SignalSetup, ctx: EventContext, rng: np.random.Generator) -> None:
        sigma, lo = self.p["sigma"], 0.01 * ctx.threshold

        def redraw(g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            # late binding: the frozen per-pixel part is whatever the setup holds at run
            # time (a threshold_mismatch listed after this effect is still honoured)
            z = rng.standard_normal((2, g.size))
            return (np.maximum(setup.theta_on[g] + sigma * z[0], lo),
                    np.maximum(setup.theta_off[g] + sigma * z[1], lo))

        setup.redraw = redraw


# --------------------------------------------------------------------- stream stage

def _poisson_events(pix: np.ndarray, rate_hz: float, ctx: EventContext,
                    rng: np.random.Generator, on_fraction: float) -> ViewEvents:
    """Homogeneous Poisson events at ``rate_hz`` on each pixel of ``pix``."""
    counts = rng.poisson(rate_hz * ctx.duration_s, size=pix.size)
    n = int(counts.sum())
    where = np.repeat(pix.astype(np.int64), counts)
    t = rng.uniform(0.0, TIME_SPAN, n)
    p = np.where(rng.random(n) < on_fraction, 1, -1).astype(np.int8)
    return ViewEvents(where, t, p)


@EVENT_EFFECTS.register
class ShotNoise(Effect):
    name = "shot_noise"
    PARAMS = {"rate_hz": Param(float, check=non_negative, expect="a rate ≥ 0 Hz per pixel"),
              "on_fraction": Param(float, 0.5, lambda v: 0 <= v <= 1, "a probability")}

    def apply(self, ev: ViewEvents, ctx: EventContext, rng: np.random.Generator) -> ViewEvents:
        noise = _poisson_events(np.arange(ctx.n_pixels), self.p["rate_hz"], ctx, rng,
                                self.p["on_fraction"])
        return merge_events(ev, noise)


@EVENT_EFFECTS.register
class HotPixels(Effect):
    name = "hot_pixels"
    PARAMS = {"fraction": Param(float, check=lambda v: 0 <= v <= 1, expect="a fraction"),
              "rate_hz": Param(float, check=non_negative, expect="a rate ≥ 0 Hz")}

    def apply(self, ev: ViewEvents, ctx: EventContext, rng: np.random.Generator) -> ViewEvents:
        k = int(round(self.p["fraction"] * ctx.n_pixels))
        hot = np.sort(rng.choice(ctx.n_pixels, size=k, replace=False))
        return merge_events(ev, _poisson_events(hot, self.p["rate_hz"], ctx, rng, 1.0))


@EVENT_EFFECTS.register
class Leak(Effect):
    name = "leak"
    PARAMS = {"rate_hz": Param(float, check=non_negative, expect="a rate ≥ 0 Hz per pixel")}

    def apply(self, ev: ViewEvents, ctx: EventContext, rng: np.random.Generator) -> ViewEvents:
        rate = self.p["rate_hz"]
        phase = rng.random(ctx.n_pixels)                       # in periods
        if rate == 0:
            return ev
        counts = np.floor(rate * ctx.duration_s - phase).astype(np.int64) + 1
        counts = np.maximum(counts, 0)
        pix = np.repeat(np.arange(ctx.n_pixels, dtype=np.int64), counts)
        k = np.arange(pix.size) - np.repeat(np.cumsum(counts) - counts, counts)
        t = (phase[pix] + k) / rate * ctx.units_per_s
        return merge_events(ev, ViewEvents(pix, t, np.ones(pix.size, np.int8)))


@EVENT_EFFECTS.register
class TimestampJitter(Effect):
    name = "timestamp_jitter"
    PARAMS = {"sigma_s": Param(float, check=non_negative, expect="a std ≥ 0 s")}

    def apply(self, ev: ViewEvents, ctx: EventContext, rng: np.random.Generator) -> ViewEvents:
        t = ev.t + rng.standard_normal(ev.t.size) * self.p["sigma_s"] * ctx.units_per_s
        return merge_events(ViewEvents(ev.pix, np.clip(t, 0.0, TIME_SPAN), ev.p))


@EVENT_EFFECTS.register
class Refractory(Effect):
    name = "refractory"
    PARAMS = {"period_s": Param(float, check=non_negative, expect="a period ≥ 0 s")}

    def apply(self, ev: ViewEvents, ctx: EventContext, rng: np.random.Generator) -> ViewEvents:
        return refractory_filter(ev, self.p["period_s"] * ctx.units_per_s)


def refractory_filter(ev: ViewEvents, period: float) -> ViewEvents:
    """Keep an event only if it comes ``≥ period`` (time units) after its pixel's last
    kept event. Greedy per pixel, vectorised over pixels: round ``k`` keeps the k-th
    surviving event of every pixel at once (binary search in a per-pixel sorted key)."""
    if ev.t.size == 0 or period <= 0:
        return ev
    order = np.lexsort((ev.t, ev.pix))
    ps, ts = ev.pix[order], ev.t[order]
    stride = TIME_SPAN + 2 * period + 1.0
    key = ps * stride + ts
    starts = np.nonzero(np.r_[True, ps[1:] != ps[:-1]])[0]
    ends = np.r_[starts[1:], ps.size]
    keep = np.zeros(ps.size, bool)
    cur, end = starts, ends
    while cur.size:
        keep[cur] = True
        nxt = np.searchsorted(key, ps[cur] * stride + ts[cur] + period, side="left")
        ok = nxt < end
        cur, end = nxt[ok], end[ok]
    sel = np.sort(order[keep])
    return ViewEvents(ev.pix[sel], ev.t[sel], ev.p[sel])
