"""The event core: every threshold crossing of each pixel's log signal, adaptively sampled.

Per pixel ``g`` the core follows ``L_g(t)`` (``log(I + ε)`` of the pixel's channel, after
an optional low-pass filter) from ``t = 0`` to ``1`` with its own step size. The
reference level starts at ``r = L_g(0)``. Between two accepted samples
``(t_a, L_a) → (t_b, L_b)`` the signal is taken as linear; while ``L_b ≥ r + θ_on`` an
ON event is emitted at

.. math:: t_e = t_a + \\frac{r + θ_{on} - L_a}{L_b - L_a}\\,(t_b - t_a),\\qquad r ← r + θ_{on}

(OFF symmetric with ``θ_off``), so every crossing gets its own interpolated float64 time.

**Sampling is adaptive** (not merely checked): a step is accepted only if the raw and
the filtered log signal change by at most ``max_log_step·θ``; otherwise it is halved
(rendering only the pixels that need it) down to ``min_step``, where a step is accepted
as is -- that only happens at true discontinuities (an edge crossing a pixel centre),
and those crossings are then stamped within ``min_step`` of the jump. After an easy step
(change ≤ half the bound) the step doubles again, up to ``max_step``, which also bounds
how long a feature can hide between two samples.

The core never loops over events in Python: each iteration advances all pixels that are
still running, and crossings are emitted in "rounds" (the k-th crossing of every pixel
in its current interval at once), usually one round per iteration.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

__all__ = ["CoreSettings", "SignalSetup", "CoreResult", "run_core", "crossings"]

log = logging.getLogger(__name__)

#: ``signal(g [N] int64, t [N] float64) -> L [N] float64`` log signal of global pixels.
SignalFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass
class CoreSettings:
    """Sampling settings (times normalised to ``[0, 1]``).

    Attributes:
        threshold: nominal θ (the step bound is ``max_log_step·threshold``).
        max_log_step: fraction of θ a step may change the log signal by.
        max_step, min_step: largest / smallest step.
    """

    threshold: float = 0.5
    max_log_step: float = 0.25
    max_step: float = 2e-3
    min_step: float = 1e-7


@dataclass
class SignalSetup:
    """What the signal-stage effects configure (arrays over all global pixels).

    Attributes:
        theta_on, theta_off: ``[P_all]`` per-pixel thresholds (frozen part).
        redraw: ``redraw(g [K]) -> (on [K], off [K])`` new thresholds after an event.
        lowpass: ``lowpass(y_a, u_a, u_b, dt) -> y_b`` filter step over ``dt`` (normalised
            time) with input linear from ``u_a`` to ``u_b`` and output ``y_a`` at the start.
        channel_weights: ``[P_all, 3]`` linear weights giving the pixel's intensity.
    """

    theta_on: np.ndarray
    theta_off: np.ndarray
    channel_weights: np.ndarray
    redraw: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
    lowpass: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None


@dataclass
class CoreResult:
    """Events (sorted by ``t``, ties by pixel) and sampling statistics.

    Attributes:
        g: ``[E]`` int64 global pixel; t: ``[E]`` float64 normalised time; p: ``[E]`` int8.
        n_samples: rendered pixel samples (accepted + rejected, including ``t = 0``).
        n_forced: steps accepted at ``min_step`` above the bound (discontinuities).
        samples: if requested, ``(g, t, L)`` of every accepted sample (filtered signal).
    """

    g: np.ndarray
    t: np.ndarray
    p: np.ndarray
    n_samples: int = 0
    n_forced: int = 0
    samples: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    iterations: int = 0
    extra: dict = field(default_factory=dict)


def crossings(g: np.ndarray, ta: np.ndarray, tb: np.ndarray, La: np.ndarray, Lb: np.ndarray,
              ref: np.ndarray, th_on: np.ndarray, th_off: np.ndarray,
              redraw: Callable | None = None) -> tuple[list, np.ndarray, np.ndarray, np.ndarray]:
    """All crossings of linear segments ``(ta, La) → (tb, Lb)`` (arrays ``[N]``).

    ``ref``, ``th_on``, ``th_off`` are the per-segment reference level and thresholds on
    entry. Returns ``(events, ref, th_on, th_off)``: ``events`` a list of
    ``(g, t, p)`` array triples (one per round) and the updated per-segment state.

    >>> ev, r, _, _ = crossings(np.array([0]), np.array([0.]), np.array([1.]),
    ...                         np.array([0.]), np.array([1.2]), np.array([0.]),
    ...                         np.array([.5]), np.array([.5]))
    >>> ev[0][1], ev[1][1], r
    (array([0.41666667]), array([0.83333333]), array([1.]))
    """
    ref, th_on, th_off = ref.copy(), th_on.copy(), th_off.copy()
    out: list = []
    rising = Lb > La
    cand = np.nonzero(np.where(rising, Lb >= ref + th_on, Lb <= ref - th_off))[0]
    while cand.size:
        up = rising[cand]
        level = np.where(up, ref[cand] + th_on[cand], ref[cand] - th_off[cand])
        a, b = La[cand], Lb[cand]
        frac = np.clip((level - a) / (b - a), 0.0, 1.0)
        te = ta[cand] + frac * (tb[cand] - ta[cand])
        out.append((g[cand], te, np.where(up, 1, -1).astype(np.int8)))
        ref[cand] = level
        if redraw is not None:
            th_on[cand], th_off[cand] = redraw(g[cand])
        more = np.where(up, b >= level + th_on[cand], b <= level - th_off[cand])
        cand = cand[more]
    return out, ref, th_on, th_off


def _skip_calm(act: np.ndarray, t_cur: np.ndarray, dt: np.ndarray, L_raw: np.ndarray,
               L_f: np.ndarray, busy: np.ndarray, tol: float, max_step: float) -> np.ndarray:
    """Move pixels in a non-busy interval (filter settled) to the start of their next busy
    interval (or 1); return the active pixels still to be rendered now."""
    K = busy.shape[1]
    k = np.minimum(np.floor(t_cur[act] * K + 1e-9).astype(np.int64), K - 1)
    calm = ~busy[act, k] & (np.abs(L_f[act] - L_raw[act]) <= tol)
    if not calm.any():
        return act
    ci, kk = act[calm], k[calm]
    later = busy[ci] & (np.arange(K)[None, :] > kk[:, None])
    j = np.where(later.any(1), later.argmax(1), K)
    t_cur[ci] = np.where(j >= K, 1.0, j / K)
    dt[ci] = max_step
    return act[~calm]


def _advance(signal: SignalFn, pix: np.ndarray, act: np.ndarray, t_cur: np.ndarray,
             dt: np.ndarray, L_raw: np.ndarray, L_f: np.ndarray, ref: np.ndarray,
             th_on: np.ndarray, th_off: np.ndarray, setup: SignalSetup,
             settings: CoreSettings, record: bool) -> tuple[list, tuple | None, int]:
    """One adaptive step of the pixels ``act`` (state arrays updated in place).

    Returns ``(events, accepted samples or None, number of forced steps)``.
    """
    bound = settings.max_log_step * settings.threshold
    ta = t_cur[act]
    tb = np.minimum(ta + dt[act], 1.0)
    tb[tb > 1.0 - 1e-12] = 1.0
    Lb = signal(pix[act], tb)
    Lfb = Lb if setup.lowpass is None else setup.lowpass(L_f[act], L_raw[act], Lb, tb - ta)
    change = np.maximum(np.abs(Lb - L_raw[act]), np.abs(Lfb - L_f[act]))
    forced = dt[act] <= settings.min_step * (1 + 1e-9)
    ok = (change <= bound) | forced
    n_forced = int(np.count_nonzero(forced & (change > bound)))
    rej = act[~ok]
    dt[rej] = np.maximum(dt[rej] * 0.5, settings.min_step)
    acc = act[ok]
    if not acc.size:
        return [], None, n_forced
    ev, ref[acc], th_on[acc], th_off[acc] = crossings(
        pix[acc], ta[ok], tb[ok], L_f[acc], Lfb[ok], ref[acc], th_on[acc], th_off[acc],
        setup.redraw)
    t_cur[acc], L_raw[acc], L_f[acc] = tb[ok], Lb[ok], Lfb[ok]
    easy = acc[change[ok] <= 0.5 * bound]
    dt[easy] = np.minimum(dt[easy] * 2.0, settings.max_step)
    return ev, ((pix[acc], tb[ok], Lfb[ok]) if record else None), n_forced


def run_core(signal: SignalFn, pix: np.ndarray, setup: SignalSetup, settings: CoreSettings,
             busy: np.ndarray | None = None, record_samples: bool = False) -> CoreResult:
    """Simulate the ideal(ised) event pixels ``pix [P]`` (global ids) over ``t ∈ [0, 1]``.

    Args:
        signal: log signal of global pixels at per-pixel times (see :data:`SignalFn`).
        pix: ``[P]`` int64 global pixel ids to simulate (static pixels may be left out).
        setup: thresholds, filter and redraw hooks (:class:`SignalSetup`).
        settings: sampling bounds (:class:`CoreSettings`).
        busy: optional ``[P, K]`` bool; ``False`` promises the pixel's raw signal is
            constant over the closed interval ``[k/K, (k+1)/K]``. A pixel at rest there
            (filter settled) jumps to its next busy interval without rendering.
        record_samples: also return every accepted sample (for tests).

    Returns:
        :class:`CoreResult` with events sorted by time.
    """
    pix = np.asarray(pix, dtype=np.int64)
    P = pix.size
    bound = settings.max_log_step * settings.threshold
    t_cur = np.zeros(P)
    dt = np.full(P, settings.max_step)
    L_raw = signal(pix, t_cur) if P else np.zeros(0)
    L_f = L_raw.copy()
    ref = L_raw.copy()
    th_on, th_off = setup.theta_on[pix].astype(np.float64), setup.theta_off[pix].astype(np.float64)
    events: list = []
    rec = [(pix.copy(), t_cur.copy(), L_f.copy())] if record_samples else []
    n_samples, n_forced, it = P, 0, 0
    running = np.arange(P)
    K = 0 if busy is None else busy.shape[1]
    while running.size:
        it += 1
        act = running
        if K:
            act = _skip_calm(running, t_cur, dt, L_raw, L_f, busy, 1e-6 * bound,
                             settings.max_step)
        if act.size:
            n_samples += act.size
            ev, rec_k, forced_k = _advance(signal, pix, act, t_cur, dt, L_raw, L_f, ref,
                                           th_on, th_off, setup, settings, record_samples)
            events.extend(ev)
            n_forced += forced_k
            if rec_k is not None:
                rec.append(rec_k)
        running = running[t_cur[running] < 1.0]
    if events:
        g = np.concatenate([e[0] for e in events])
        t = np.concatenate([e[1] for e in events])
        p = np.concatenate([e[2] for e in events])
        order = np.lexsort((g, t))
        g, t, p = g[order], t[order], p[order]
    else:
        g, t, p = np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int8)
    samples = None
    if record_samples:
        samples = tuple(np.concatenate([r[i] for r in rec]) for i in range(3))
    if n_forced:
        log.debug("event core: %d steps at min_step exceeded the log-step bound "
                  "(discontinuities)", n_forced)
    return CoreResult(g, t, p, n_samples, n_forced, samples, it)
