"""Events of the training views: scene → log signal → event core → stream effects.

The pixel's signal is ``L = log(w·I + ε)`` with ``I`` the linear RGB radiance of its
pixel (supersampled), ``w`` its channel weights (one-hot RGGB with the ``bayer`` effect,
``(1/3, 1/3, 1/3)`` -- the grey level -- without) and ``ε = tonemap_eps``. The renderer
is float64 throughout; nothing is quantised before crossing detection.

Render only what is needed: the time axis is cut into intervals of two ``max_step``;
a pixel is rendered in an interval only if one of its rays meets the bounding sphere of
a moving object over that interval (:meth:`PixelRenderer.activity`), otherwise its
signal is provably constant there and the core skips it. Stream effects such as shot
noise still act on every pixel.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import torch

from eventrecon import TIME_SPAN
from eventrecon.data.types import EventStream
from eventrecon.sim.config import effect_rng
from eventrecon.sim.event_effects import EventContext, ViewEvents
from eventrecon.sim.ideal import CoreResult, CoreSettings, SignalSetup, run_core
from eventrecon.sim.raytrace import PixelRenderer
from eventrecon.sim.spec import SceneSpec

__all__ = ["simulate_events", "event_context", "to_stream"]

log = logging.getLogger(__name__)


def event_context(spec: SceneSpec, n_views: int) -> EventContext:
    """The :class:`EventContext` of a spec's training views."""
    return EventContext(spec.width, spec.height, n_views, spec.tonemap_eps, spec.threshold,
                        spec.duration_s)


def to_stream(ev: ViewEvents, width: int) -> EventStream:
    """Compact dtypes of the published layout (x, y int16; t float64; p int8)."""
    return EventStream((ev.pix % width).astype(np.int16), (ev.pix // width).astype(np.int16),
                       ev.t.astype(np.float64), ev.p.astype(np.int8))


def simulate_events(spec: SceneSpec, prend: PixelRenderer, record_samples: bool = False
                    ) -> tuple[list[EventStream], CoreResult]:
    """Simulate every view of ``prend.cams`` with the spec's event effects.

    Returns:
        ``(streams, core)``: one :class:`EventStream` per view (time units, sorted) and
        the core's result (ideal-stage events in normalised time, sampling statistics).
    """
    V = len(prend.cams)
    ctx = event_context(spec, V)
    n_all = V * ctx.n_pixels
    setup = SignalSetup(np.full(n_all, spec.threshold), np.full(n_all, spec.threshold),
                        np.full((n_all, 3), 1.0 / 3.0))
    signal_fx = [e for e in spec.event_effects if e.stage == "signal"]
    stream_fx = [e for e in spec.event_effects if e.stage == "stream"]
    for e in signal_fx:
        e.configure(setup, ctx, effect_rng(spec.seed, "events", e.name, e.occurrence))
    weights = torch.as_tensor(setup.channel_weights)
    eps = spec.tonemap_eps

    def signal(g: np.ndarray, t: np.ndarray) -> np.ndarray:
        gt = torch.from_numpy(g)
        rgb = prend.radiance(gt, torch.from_numpy(t))
        return torch.log((rgb * weights[gt]).sum(-1) + eps).numpy()

    settings = CoreSettings(spec.threshold, spec.max_log_step, spec.max_step, spec.min_step)
    t0 = time.perf_counter()
    pix, busy = prend.activity(max(1, math.ceil(0.5 / spec.max_step)))
    core = run_core(signal, pix, setup, settings, busy=busy, record_samples=record_samples)
    sec = time.perf_counter() - t0
    core.extra.update(seconds=sec, dynamic_pixels=int(pix.size))
    log.info("event core: %d events, %d pixel samples (%d dynamic pixels, %d iterations, "
             "%d forced steps) in %.2f s", core.t.size, core.n_samples, pix.size,
             core.iterations, core.n_forced, sec)
    view = core.g // ctx.n_pixels
    order = np.argsort(view, kind="stable")
    bounds = np.searchsorted(view[order], np.arange(V + 1))
    streams = []
    for v in range(V):
        sel = order[bounds[v]:bounds[v + 1]]
        ev = ViewEvents(core.g[sel] % ctx.n_pixels, core.t[sel] * TIME_SPAN, core.p[sel])
        for e in stream_fx:
            ev = e.apply(ev, ctx, effect_rng(spec.seed, "events", e.name, e.occurrence, v))
        streams.append(to_stream(ev, spec.width))
    return streams, core
