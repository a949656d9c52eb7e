"""The event core: every threshold crossing of each pixel's log signal, adaptively sampled.

Per pixel ``g`` the core follows ``L_g(t)`` (``log(I + ε)`` of the pixel's channel, after
an optional low-pass filter) from ``t = 0`` to ``1`` with its own step size. The
reference level starts at ``r = L_g(0)``; the samples, joined by straight legs, form the
pixel's *path*, and while a leg reaches ``L ≥ r + θ_on`` an ON event is emitted and
``r ← r + θ_on`` (OFF alike with ``θ_off``) -- at a float64 time interpolated on the
pixel's own samples (:mod:`~eventrecon.sim.crossing`: the polynomial through the leg and
up to two neighbours on each side, a Newton step from its quadratic part's root).

**Sampling is adaptive.** A sample is kept only if the raw and the filtered signal change
by at most ``β = max_log_step·θ`` and the slope changes by at most ``max_curvature·β``
per step (the second difference ``|ΔL_k − ΔL_{k−1}·h_k/h_{k−1}| ≤ max_curvature·β``;
a straight leg then cuts an extremum by at most ``max_curvature·β/8``). Each iteration
evaluates a block of up to ``block`` samples per pixel (steps ``h``, or ``h, 2h, 4h, …``
after an easy block; at most ``max_step``) and keeps the prefix before the first rejected
one. The next step aims at ``0.95·β`` per step, predicted from the last step and its
change; a rejection shrinks it in proportion. A jump (a change above ``4β`` that does not
shrink with the step) is bracketed by bisection, one sample per iteration, down to
``min_step``, where a sample is kept as is: only true discontinuities get there, and
their crossings are stamped within ``min_step`` of the jump.

**Turns.** Where the steps change sign the extremum between samples is located (parabolic
interpolation, evaluated) whenever a level lies within reach, and a level the true
signal passes by more than about ``turn_tol·θ`` is crossed (:mod:`~eventrecon.sim.paths`).

The rules run as whole-array numpy passes over blocks ``[M, N]`` of the running pixels
(:mod:`~eventrecon.sim.paths`).

**Order.** Each pixel's events come in time order; the events of all pixels are put in
``(t, g)`` order by one ``lexsort`` (:func:`~eventrecon.sim.merge.merge_by_time`).
:func:`frame_events` is the frame-fed counterpart: the crossings of the log signal linear
between given frames.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from eventrecon.sim.core_settings import STEP_TARGET, CoreSettings, SignalSetup
from eventrecon.sim.merge import merge_by_time, time_order
from eventrecon.sim.paths import PathState, commit

__all__ = ["CoreSettings", "SignalSetup", "CoreResult", "run_core", "crossings", "frame_events"]

log = logging.getLogger(__name__)

#: ``signal(g [N] int64, t [N] float64) -> L [N] float64`` log signal of global pixels.
SignalFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass
class CoreResult:
    """Events (sorted by ``t``, ties by pixel) and sampling statistics.

    Attributes:
        g: ``[E]`` int64 global pixel; t: ``[E]`` float64 normalised time; p: ``[E]`` int8.
        n_samples: rendered pixel samples (accepted + rejected + turn refinements,
            including ``t = 0``, and the repeats of the last sample that fill a block cut
            short where the whole block is evaluated).
        n_forced: samples accepted at ``min_step`` above the bounds (discontinuities).
        samples: if requested, ``(g, t, L)`` of every path sample (filtered signal).
        extra: ``turn_samples`` (refinement evaluations) and what callers add.
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


def frame_events(frames: np.ndarray | Sequence[np.ndarray], times: np.ndarray,
                 theta_on: float | np.ndarray, theta_off: float | np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame-fed emission: the crossings of the log signal linear between frames.

    Args:
        frames: ``[T, P]`` float64 log frames ``L_k`` at ``times[k]`` (or ``T`` arrays).
        times: ``[T]`` increasing frame times.
        theta_on, theta_off: thresholds, scalars or ``[P]``.

    Returns:
        ``(g [E] int64, t [E] float64, p [E] int8)`` in ``(t, g)`` order: from frame ``k``
        to ``k+1`` every crossing of ``r + θ_on`` (then ``r ← r + θ_on``; OFF alike) at
        ``t_k + (r + θ_on − L_k)/(L_{k+1} − L_k)·(t_{k+1} − t_k)``, as :func:`crossings`.
        Each interval's events are ordered by :func:`~eventrecon.sim.merge.time_order`;
        the intervals follow each other, so no global sort is needed.

    >>> g, t, p = frame_events(np.array([[0., 0.], [1.2, -0.6]]), np.array([0., 1.]), .5, .5)
    >>> g.tolist(), t.round(4).tolist(), p.tolist()
    ([0, 0, 1], [0.4167, 0.8333, 0.8333], [1, 1, -1])
    """
    times = np.asarray(times, dtype=np.float64)
    La = np.asarray(frames[0], dtype=np.float64)
    on, off = (np.asarray(th, dtype=np.float64) for th in (theta_on, theta_off))
    hi, lo = La + on, La - off                   # ref ± θ; ref − θ_off < L_a < ref + θ_on
    parts: list = []
    for k in range(times.size - 1):
        Lb = np.asarray(frames[k + 1], dtype=np.float64)
        ta, dt = times[k], times[k + 1] - times[k]
        cand = np.flatnonzero((Lb >= hi) | (Lb <= lo))
        gs, ts, ps = [], [], []
        while cand.size:
            b, h_c, l_c = Lb[cand], hi[cand], lo[cand]
            up = b >= h_c
            level = np.where(up, h_c, l_c)
            gs.append(cand)
            ts.append(ta + np.minimum((level - La[cand]) / (b - La[cand]), 1.0) * dt)
            ps.append(np.where(up, np.int8(1), np.int8(-1)))
            hi[cand] = level + (on if on.ndim == 0 else on[cand])
            lo[cand] = level - (off if off.ndim == 0 else off[cand])
            cand = cand[np.where(up, b >= hi[cand], b <= lo[cand])]
        if gs:
            g, t, p = np.concatenate(gs), np.concatenate(ts), np.concatenate(ps)
            o = time_order(t, g)
            parts.append((g[o], t[o], p[o]))
        La = Lb
    if not parts:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int8)
    g, t, p = (np.concatenate([q[i] for q in parts]) for i in range(3))
    # intervals follow in time; only stamps rounded onto a frame time may tie across two
    for b in np.flatnonzero((t[1:] == t[:-1]) & (g[1:] < g[:-1])):
        a, e = np.searchsorted(t, t[b]), np.searchsorted(t, t[b], side="right")
        o = a + np.argsort(g[a:e], kind="stable")
        g[a:e], t[a:e], p[a:e] = g[o], t[o], p[o]
    return g.astype(np.int64, copy=False), t, p


# ----------------------------------------------------------------- the adaptive core
# Blocks are laid out [sample, pixel] (one row per sample index, contiguous); ``sel``
# addresses pixels of the state (a slice or an index array).

_STEPS = np.arange(1.0, 65.0)[:, None]
_POW2 = 2.0 ** np.arange(64)
_FIRST = np.arange(64, 0, -1, dtype=np.int8)[:, None]   # M − k: first flagged row k


def _sample(signal: SignalFn, st: PathState, sel, setup: SignalSetup, s: CoreSettings,
            stats: dict) -> tuple:
    """Evaluate a block ``[M, N]`` of the pixels ``sel``, keep its prefix before the first
    rejected sample, choose the next step. Returns ``(T, Lr, Lf, D, n_acc [N])``, ``D``
    the steps of ``Lf``."""
    M, bound = s.block, s.max_log_step * s.threshold
    h0, t0, gr, n_valid = st.h[sel].copy(), st.t[-1, sel], st.grow[sel], st.m[sel]
    N, ar = h0.size, np.arange(h0.size)
    T = t0 + _STEPS[:M] * h0
    odd = gr | (n_valid < M)                 # steps h, 2h, 4h, … (at most max_step)
    if gr.any():
        T[:, gr] = t0[gr] + np.cumsum(np.minimum(_POW2[:M, None] * h0[gr], s.max_step), 0)
    if T[-1].max() >= 1.0 - 1e-12:
        end = T >= 1.0 - 1e-12
        T[end] = 1.0
        n_valid = np.minimum(n_valid, M - end.sum(0) + 1)
        odd |= end[-1]
    short = np.flatnonzero(n_valid < M)      # rows beyond n_valid repeat the last sample
    if short.size:
        T[:, short] = T[np.minimum(np.arange(M)[:, None], n_valid[short] - 1), short]
    g = np.tile(st.pix[sel], M)
    if short.size and n_valid.sum() < 0.8 * N * M:
        kk = np.flatnonzero(_STEPS[:M] <= n_valid)
        Lr = np.empty((M, N))
        Lr.ravel()[kk] = signal(g[kk], T.ravel()[kk])
        Lr[:, short] = Lr[np.minimum(np.arange(M)[:, None], n_valid[short] - 1), short]
        stats["n_samples"] += kk.size
    else:
        Lr = signal(g, T.ravel()).reshape(M, N)
        stats["n_samples"] += N * M
    Lf = Lr
    if setup.lowpass is not None:
        dT = np.diff(T, axis=0, prepend=t0[None])
        Lf, yf, yr = np.empty_like(Lr), st.Lf[-1, sel], st.Lr[-1, sel]
        for k in range(M):
            yf = Lf[k] = setup.lowpass(yf, yr, Lr[k], dT[k])
            yr = Lr[k]
    D = np.empty_like(Lf)
    D[0] = Lf[0] - st.Lf[-1, sel]
    np.subtract(Lf[1:], Lf[:-1], out=D[1:])
    # R = max(|ΔL|, |Δ²L|/max_curvature): a sample is kept while R ≤ β
    R = np.empty_like(D)
    np.subtract(D[1:], D[:-1], out=R[1:])
    R[0] = D[0] - st.slope[sel] * (T[0] - t0)
    odd = np.flatnonzero(odd)
    if odd.size:                             # unequal steps: compare slopes
        dT = np.diff(T[:, odd], axis=0, prepend=t0[None, odd])
        with np.errstate(divide="ignore", invalid="ignore"):
            R[1:, odd] = D[1:, odd] - D[:-1, odd] * (dT[1:] / dT[:-1])
    np.abs(R, out=R)
    if s.max_curvature != 1.0:
        R *= 1.0 / s.max_curvature
    np.fmax(R, np.abs(D), out=R)
    if setup.lowpass is not None:
        np.maximum(R, np.abs(np.diff(Lr, axis=0, prepend=st.Lr[-1, sel][None])), out=R)
    n_acc = np.minimum(M - ((R > bound) * _FIRST[-M:]).max(0), n_valid)
    forced = h0 <= s.min_step * (1 + 1e-9)
    if forced.any():
        stats["n_forced"] += int(np.count_nonzero((R > bound)[:, forced] &
                                                  (np.arange(M)[:, None] < n_valid[forced])))
        n_acc[forced] = n_valid[forced]
    # next step: shrink in proportion to a rejected sample; after a kept block predict
    # the change per step over the next block from the last step and its change
    rej = n_acc < n_valid
    Tf, Df, Rf = T.ravel(), D.ravel(), R.ravel()

    def step(k):                              # length of the step to flat index k
        return Tf[k] - np.where(k < N, t0, Tf[np.maximum(k - N, 0)])
    kl = np.maximum(n_acc - 1, 0) * N + ar                    # the last kept sample
    k = np.where(rej, np.minimum(n_acc, M - 1) * N + ar, kl)  # or the rejected one
    hk, hl, Dk, Rk = step(k), step(kl), Df[k], Rf[k]
    Ek = Dk - np.where(k < N, st.slope[sel] * hk, Df[np.maximum(k - N, 0)])
    with np.errstate(divide="ignore", invalid="ignore"):
        pred = np.fmax(np.maximum(np.abs(Dk + Ek), np.abs(Dk + M * Ek)), Rk) / bound
        f = np.where(rej, np.clip(STEP_TARGET * bound / Rk, 0.1, 0.7),
                     np.clip(STEP_TARGET / pred, 0.5, 2.0))
        slope = np.where(Rf[kl] > bound, np.nan, Df[kl] / hl)
    # a jump (a rejected change above 4β that does not shrink with the step) is
    # bracketed by bisection, one sample per iteration, down to min_step
    brk = ~forced & np.where(rej, Rk > 4 * bound, st.brk[sel])
    h = np.clip(hk * np.where(brk, 0.5, f), s.min_step, s.max_step)
    st.h[sel], st.brk[sel] = h, brk
    st.m[sel] = np.where(brk, 1, np.where(rej, np.clip(n_acc + 1, 2, M),
                                          np.minimum(2 * n_valid, M)))
    st.grow[sel] = ~rej & (f >= 2.0) & (R.max(0) <= 0.5 * bound) & (h < s.max_step)
    st.slope[sel] = np.where(n_acc > 0, slope, st.slope[sel])
    return T, Lr, Lf, D, n_acc


def _calm(st: PathState, tol: float, max_step: float, block: int
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split the pixels into those to sample and those at rest in a non-busy interval
    (filter settled), which get their next busy start (or 1) as a flat sample.

    Returns ``(to_sample, calm, t_next)`` (index arrays and times)."""
    K = st.busy.shape[1]
    k = np.minimum(np.floor(st.t[-1] * K + 1e-9).astype(np.int64), K - 1)
    calm = ~st.busy[st.row, k] & (np.abs(st.Lf[-1] - st.Lr[-1]) <= tol)
    ci = np.flatnonzero(calm)
    later = st.busy[st.row[ci]] & (np.arange(K)[None, :] > k[ci, None])
    j = np.where(later.any(1), later.argmax(1), K)
    st.h[ci], st.m[ci], st.grow[ci], st.slope[ci] = max_step, block, False, np.nan
    st.brk[ci] = False
    return np.flatnonzero(~calm), ci, np.where(j >= K, 1.0, j / K)


def _finite(signal: SignalFn) -> SignalFn:
    """``signal``, raising one clear error where it returns a non-finite log value (no
    crossing is defined there; an infinite one would never stop emitting)."""
    def checked(g: np.ndarray, t: np.ndarray) -> np.ndarray:
        L = signal(g, t)
        with np.errstate(over="ignore"):         # one pass: NaN and ±inf carry into the
            if np.isfinite(np.add.reduce(L, axis=None)):   # sum (an overflow of finite
                return L                                    # values: checked below)
        bad = np.flatnonzero(~np.isfinite(L))
        if bad.size:
            k = bad[0]
            raise ValueError(f"event core: the log signal returned {bad.size} non-finite "
                             f"value(s), first {L[k]} at pixel {int(g[k])}, t = {t[k]:.6g}; "
                             "expected finite values (log(I + eps) with eps > 0)")
        return L
    return checked


def _check_thresholds(setup: SignalSetup) -> None:
    """One clear error for a threshold ≤ 0 (a zero one would emit forever)."""
    for name in ("theta_on", "theta_off"):
        th = getattr(setup, name)
        if th.size and not (np.min(th) > 0):
            raise ValueError(f"SignalSetup.{name}: expected thresholds > 0, got a minimum of "
                             f"{np.min(th)}")


def _follow(signal: SignalFn, pix: np.ndarray, setup: SignalSetup, settings: CoreSettings,
            busy: np.ndarray | None, record_samples: bool, stats: dict
            ) -> tuple[list, list | None, int]:
    """The adaptive loop of :func:`run_core`: every pixel's path followed from ``t = 0``
    to ``1``. Returns ``(event parts, recorded samples or None, iterations)``."""
    L0 = signal(pix, np.zeros(pix.size)) if pix.size else np.zeros(0)
    st = PathState(pix, L0, setup, settings, busy)
    out: list = []
    rec = [(pix.copy(), np.zeros(pix.size), L0.copy())] if record_samples else None
    stats["n_samples"] += pix.size
    tol = 1e-6 * settings.max_log_step * settings.threshold
    it = 0
    while st.pix.size:
        it += 1
        sel = slice(None)
        if busy is not None:
            sel, calm, t_next = _calm(st, tol, settings.max_step, settings.block)
            if calm.size:
                commit(signal, st, calm, t_next[None], st.Lr[-1, calm][None],
                       st.Lf[-1, calm][None], np.zeros((1, calm.size)),
                       np.ones(calm.size, np.int64), setup, settings, stats, out, rec)
        if isinstance(sel, slice) or sel.size:
            T, Lr, Lf, D, n_acc = _sample(signal, st, sel, setup, settings, stats)
            commit(signal, st, sel, T, Lr, Lf, D, n_acc, setup, settings, stats, out, rec)
        running = st.t[-1] < 1.0
        if not running.all():
            st.keep(running)
    return out, rec, it


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
        record_samples: also return every path sample (for tests).

    Returns:
        :class:`CoreResult` with events sorted by time, ties by pixel.
    """
    pix = np.asarray(pix, dtype=np.int64)
    stats = {"n_samples": 0, "n_forced": 0, "turn_samples": 0}
    signal = _finite(signal)
    _check_thresholds(setup)
    out, rec, it = _follow(signal, pix, setup, settings, busy, record_samples, stats)
    g, t, p = merge_by_time(out) if out else (np.zeros(0, np.int64), np.zeros(0),
                                              np.zeros(0, np.int8))
    samples = None
    if rec is not None:
        samples = tuple(np.concatenate([r[i] for r in rec]) for i in range(3))
    if stats["n_forced"]:
        log.debug("event core: %d samples at min_step exceeded the bounds "
                  "(discontinuities)", stats["n_forced"])
    return CoreResult(g, t, p, stats["n_samples"], stats["n_forced"], samples, it,
                      {"turn_samples": stats["turn_samples"]})
