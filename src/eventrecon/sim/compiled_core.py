"""The event core's per-pixel bookkeeping as compiled loops (numba).

:func:`~eventrecon.sim.ideal.run_core` in numpy spends most of its time on bookkeeping,
not on the signal: every iteration it moves blocks ``[M, N]`` of samples through dozens
of whole-array operations (acceptance, step prediction, emission leg by leg, turn
detection, crossing times). Here the same rules run as one loop per pixel, compiled, and
the signal stays a vectorised numpy call. One iteration is

1. :func:`_plan` -- each pixel's next block of sample times (``h, 2h, …`` or ``h, 2h,
   4h, …``, clipped at ``t = 1``), flattened into buffers kept for the whole run;
2. ``signal(g, t)`` on all of them, in cache-sized blocks (:data:`SIGNAL_BATCH`);
3. :func:`_step` -- per pixel: the accepted prefix (``|ΔL| ≤ β`` and
   ``|Δ²L| ≤ max_curvature·β``), the next step and block length, then the path
   ``s_{−4} … s_0, new samples`` and its smooth turns. A pixel with no turn that may
   reach a level emits its crossings at once (``compiled_paths.commit_path``); the
   others wait;
4. for the waiting pixels, the vertex refinement of
   :func:`~eventrecon.sim.compiled_paths.refine_turns` (the rule of
   :func:`eventrecon.sim.paths.refine_turns`, compiled), then :func:`_commit_turned`
   emits each from its path with the refined points merged in where one gained a
   crossing, from the original path otherwise.

Every rule and every floating-point expression is the numpy core's
(:mod:`eventrecon.sim.ideal`, :mod:`eventrecon.sim.paths`), so both give the same events bit
for bit (``tests/test_sim_turns.py``). The compiled engine covers the ideal pixel: no
low-pass filter, no re-drawn thresholds, no ``busy`` map and no sample recording.
``run_core`` falls back to numpy for the rest -- which includes every scene the simulator
renders (:func:`~eventrecon.sim.event_sim.simulate_events` always passes a ``busy`` map).
That is deliberate: there the renderer costs ~20× the core's bookkeeping, and a rendered
signal evaluated in other batches may differ in the last bit (vectorised and scalar
``exp``/``log`` paths), which would change published datasets without a ``SIM_VERSION``
bump. The compiled engine serves analytic signals: the benchmarks, and users calling
:func:`~eventrecon.sim.ideal.run_core` on their own. numba compiles the loops on first use
(a few seconds) and caches them next to this file.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from eventrecon.sim.compiled_paths import (
    clip,
    commit_path,
    find_turns,
    gather_turns,
    queue_turns,
    refine_turns,
    room,
)
from eventrecon.sim.core_settings import STEP_TARGET
from eventrecon.sim.crossing import FIRST_LEG, KEEP
from eventrecon.sim.jit import AVAILABLE, larger, njit_borrowing, njit_inline, smaller

__all__ = ["AVAILABLE", "run_compiled"]

#: Samples per call of the signal: its passes (gathers, arithmetic, ``sin``, ``log``) then
#: run on blocks that stay in the core's L2 cache between passes instead of streaming the
#: whole iteration's samples (about 0.7 M at first) through memory once per pass.
SIGNAL_BATCH = 1 << 15

#: Finished pixels are dropped from the state once fewer than this share still runs; until
#: then they only skip their turn in :func:`_plan` and :func:`_step`.
DROP = 0.75


@njit_borrowing
def _plan(pix, t_last, h, grow, m, M, max_step, G, T, start, n_valid, odd):
    """Sample times of each pixel's next block, flattened, into the caller's buffers.

    Pixel ``i`` samples ``t_i + h_i·(1, 2, …)``, or after an easy block the partial sums
    of ``min(2^k·h_i, max_step)``, at most ``m_i`` of them; a time from ``1 − 1e-12`` on
    is 1 and ends the block. A pixel that has reached ``t = 1`` samples nothing. Writes
    ``G, T`` (``[≥ N·M]``; pixel ``i`` samples ``T[start[i]:start[i+1]]``, ``G`` its
    global id ``pix[i]`` there), ``start [≥ N + 1]``, ``n_valid [≥ N]`` and ``odd [≥ N]``
    (unequal steps). The buffers live as long as the run (:class:`_PlanBuffers`), so no
    iteration maps fresh memory. Returns ``Σ n``, the samples written."""
    N = h.size
    start[0] = 0
    j = 0
    for i in range(N):
        t0, h0, s, p2, k = t_last[i], h[i], 0.0, 1.0, 0
        ended = t0 >= 1.0
        while k < m[i] and not ended:
            if grow[i]:
                s += smaller(p2 * h0, max_step)
                p2 *= 2.0
                t = t0 + s
            else:
                t = t0 + (k + 1.0) * h0
            if t >= 1.0 - 1e-12:
                t, ended = 1.0, True
            T[j], G[j] = t, pix[i]
            j += 1
            k += 1
        n_valid[i] = k
        odd[i] = grow[i] or m[i] < M or ended
        start[i + 1] = j
    return j


class _PlanBuffers:
    """The arrays :func:`_plan` fills and the signal's values, allocated once per run for
    ``P`` pixels and blocks of ``M`` and reused by every iteration (views of their first
    ``N`` or ``Σ n`` elements): allocated afresh, one iteration's several MB were faulted
    in again (~37 000 minor faults in a fresh process's 346×260 grating; now ~2 000)."""

    def __init__(self, P: int, M: int):
        self.M, self.G, self.T = M, np.empty(P * M, np.int64), np.empty(P * M)
        self.start, self.n_valid = np.empty(P + 1, np.int64), np.empty(P, np.int64)
        self.odd, self.L = np.empty(P, np.bool_), np.empty(P * M)

    def plan(self, pix, t_last, h, grow, m, max_step) -> tuple[np.ndarray, ...]:
        """:func:`_plan` into the buffers: ``(G [Σ n], T [Σ n], start [N + 1],
        n_valid [N], odd [N])``."""
        N = h.size
        j = _plan(pix, t_last, h, grow, m, self.M, max_step, self.G, self.T, self.start,
                  self.n_valid, self.odd)
        return self.G[:j], self.T[:j], self.start[:N + 1], self.n_valid[:N], self.odd[:N]


@njit_inline
def _accept(i, T, s0, nv, odd, D, R, M, bound, min_step, max_step, max_curvature, st_t, h,
            m, brk, grow, slope):
    """The accepted prefix of pixel ``i``'s block (``D [nv]`` its steps of L, ``odd``:
    unequal steps) and its next step, block length and growth flag (``_sample`` of the
    numpy core): a sample is kept while ``R = max(|ΔL|, |Δ²L|/max_curvature) ≤ β``
    (``bound``); at ``min_step`` every sample is kept (a discontinuity). The next step
    aims at 0.95·β from the last step and its change; a rejection shrinks it in
    proportion; a jump (a change above 4β) is bisected one sample per iteration.

    Returns ``(n_acc, samples forced over the bounds, slope of the last kept step)``."""
    t0, h0 = st_t[i, KEEP - 1], h[i]
    Rmax = 0.0
    n_acc, n_rej = nv, 0
    for k in range(nv):
        if k == 0:
            r = D[0] - slope[i] * (T[s0] - t0)
        elif odd:
            dT1 = T[s0 + k] - T[s0 + k - 1]
            dT0 = T[s0 + k - 1] - (t0 if k == 1 else T[s0 + k - 2])
            r = D[k] - D[k - 1] * (dT1 / dT0)
        else:
            r = D[k] - D[k - 1]
        r = abs(r)
        if max_curvature != 1.0:
            r *= 1.0 / max_curvature
        if not (r >= abs(D[k])):                 # np.fmax: NaN gives way
            r = abs(D[k])
        R[k] = r
        Rmax = larger(Rmax, r)
        if r > bound:
            n_rej += 1
            if n_acc == nv:
                n_acc = k
    forced = h0 <= min_step * (1 + 1e-9)
    if forced:
        n_acc = nv
    rej = n_acc < nv
    kl = larger(n_acc - 1, 0)
    k = n_acc if rej else kl
    hk = T[s0 + k] - (t0 if k == 0 else T[s0 + k - 1])
    hl = T[s0 + kl] - (t0 if kl == 0 else T[s0 + kl - 1])
    Dk, Rk = D[k], R[k]
    Ek = Dk - (slope[i] * hk if k == 0 else D[k - 1])
    a = larger(abs(Dk + Ek), abs(Dk + M * Ek))
    if math.isnan(a):
        a = Rk
    pred = larger(a, Rk) / bound
    if rej:
        f = clip(STEP_TARGET * bound / Rk, 0.1, 0.7)
    else:
        f = clip(STEP_TARGET / pred, 0.5, 2.0)
    new_slope = np.nan if R[kl] > bound else D[kl] / hl
    b = (not forced) and (Rk > 4 * bound if rej else brk[i])
    hn = clip(hk * (0.5 if b else f), min_step, max_step)
    h[i], brk[i] = hn, b
    if b:
        m[i] = 1
    elif rej:
        m[i] = smaller(larger(n_acc + 1, 2), M)
    else:
        m[i] = smaller(2 * nv, M)
    grow[i] = (not rej) and f >= 2.0 and Rmax <= 0.5 * bound and hn < max_step
    return n_acc, (n_rej if forced else 0), new_slope


@njit_borrowing
def _step(i0, T, start, n_valid, odd, L, pix, st_t, st_L, h, m, brk, grow, slope, ref, on,
          off, M, threshold, max_log_step, min_step, max_step, max_curvature, turn_tol,
          Wt, WL, wlen, wdone, tr_i, tr_c, tr_sig, tr_gap, n_turns, bg, bt, bp, n, R, D, pt,
          pL, ct, cv):
    """Accept, choose the next step and commit the pixels ``i0, i0 + 1, …`` (module
    docstring, step 3), their events into ``bg, bt, bp`` from ``n`` on.

    A pixel with smooth turns of which one may reach a level is not committed: its path
    goes to ``Wt, WL`` (``[N, M + KEEP]``; ``wlen``, ``wdone``) and its turns to ``tr_*``
    from ``n_turns`` on. Stops before a pixel whose events might not fit. ``R, D``
    (``[M]``), ``pt, pL`` (``[M + KEEP]``), ``ct [M + KEEP]`` int64 and
    ``cv [M + KEEP, 3]`` are scratch space (:func:`_scratch`).

    Returns ``(next pixel, n, n_turns, n_forced)``; all done when the first is ``N``."""
    N = h.size
    bound = max_log_step * threshold
    tol = 0.5 * turn_tol * threshold
    cbound = max_curvature * max_log_step * threshold
    n_forced = 0
    for i in range(i0, N):
        s0, nv, prev = start[i], n_valid[i], st_L[i, KEEP - 1]
        if nv == 0:                              # reached t = 1 (not yet dropped)
            continue
        var = 0.0                                # bounds the events of the path
        for k in range(FIRST_LEG, KEEP - 1):     # its legs held back
            var += abs(st_L[i, k + 1] - st_L[i, k])
        for k in range(nv):
            D[k] = L[s0 + k] - (prev if k == 0 else L[s0 + k - 1])
            var += abs(D[k])
        if n + var / smaller(on[i], off[i]) + nv + KEEP > bg.size:   # floats: no overflow
            return i, n, n_turns, n_forced      # the caller makes room
        n_acc, forced, new_slope = _accept(i, T, s0, nv, odd[i], D, R, M, bound, min_step,
                                           max_step, max_curvature, st_t, h, m, brk, grow,
                                           slope)
        n_forced += forced
        if n_acc == 0:
            continue
        slope[i] = new_slope
        # the path s_{−4} … s_0, accepted samples
        for k in range(KEEP):
            pt[k], pL[k] = st_t[i, k], st_L[i, k]
        for k in range(n_acc):
            pt[KEEP + k], pL[KEEP + k] = T[s0 + k], L[s0 + k]
        length = n_acc + KEEP
        done = 1 if pt[length - 1] >= 1.0 else 0
        nt = find_turns(pt, pL, length, done, cbound, tol, ct, cv)
        if nt and queue_turns(i, pt, pL, nt, ct, cv, ref[i], on[i], off[i], tol, tr_i,
                               tr_c, tr_sig, tr_gap, n_turns):
            n_turns += nt                        # refined by the caller
            for k in range(length):
                Wt[i, k], WL[i, k] = pt[k], pL[k]
            wlen[i], wdone[i] = length, done
        else:
            n = commit_path(pt, pL, length, done, i, pix[i], st_t, st_L, ref, on, off, bg, bt,
                             bp, n)
    return N, n, n_turns, n_forced


@njit_borrowing
def _commit_turned(a, tr_i, tr_tb, tr_Lb, tr_moved, tr_gap, Wt, WL, wlen, wdone, pix, st_t,
                   st_L, ref, on, off, bg, bt, bp, n, pt, pL, xt, xL):
    """Commit the pixels whose turns were refined (turns grouped by pixel, from turn ``a``
    on): with the best points of their moved turns merged into the path in time order
    (ties after the path's own point) where one of them gained a crossing (``moved`` and
    ``gap ≤ 0``), from the original path otherwise. Stops before a pixel whose events
    might not fit. ``pt, pL`` (``[M + KEEP + K]``) and ``xt, xL`` (``[K]``) are scratch
    space. Returns ``(next turn, n)``; all done when the first is ``len(tr_i)``."""
    K = tr_i.size
    while a < K:
        i, e, redo = tr_i[a], a, False
        while e < K and tr_i[e] == i:
            redo |= tr_moved[e] and tr_gap[e] <= 0
            e += 1
        length, nx = wlen[i], 0
        for j in range(a, e):                    # the moved points, stably by time
            if redo and tr_moved[j]:
                k = nx
                while k > 0 and xt[k - 1] > tr_tb[j]:
                    xt[k], xL[k] = xt[k - 1], xL[k - 1]
                    k -= 1
                xt[k], xL[k] = tr_tb[j], tr_Lb[j]
                nx += 1
        m, c, k = 0, 0, 0                        # merged with the path
        while c < length or k < nx:
            if k == nx or (c < length and Wt[i, c] <= xt[k]):
                pt[m], pL[m] = Wt[i, c], WL[i, c]
                c += 1
            else:
                pt[m], pL[m] = xt[k], xL[k]
                k += 1
            m += 1
        if n + room(pL, m, smaller(on[i], off[i])) > bg.size:
            return a, n
        n = commit_path(pt, pL, m, wdone[i], i, pix[i], st_t, st_L, ref, on, off, bg, bt, bp,
                         n)
        a = e
    return K, n


def _in_batches(signal: Callable, g: np.ndarray, t: np.ndarray,
                out: np.ndarray | None = None) -> np.ndarray:
    """``signal(g, t)`` (``[N]`` each) called on consecutive blocks of at most
    :data:`SIGNAL_BATCH` samples. The signal is elementwise (a sample's value depends on
    its own pixel and time only, as the core's other calls on any subset already assume),
    so the values, and their dtype (the first block's), are those of one call. ``out``
    (``[≥ N]``): where the blocks go when it has that dtype (the result is then a view of
    it); a new array otherwise."""
    n = t.size
    if n <= SIGNAL_BATCH:
        return signal(g, t)
    first = signal(g[:SIGNAL_BATCH], t[:SIGNAL_BATCH])
    fits = out is not None and out.dtype == first.dtype and out.size >= n
    L = out[:n] if fits else np.empty(n, first.dtype)
    L[:SIGNAL_BATCH] = first
    for a in range(SIGNAL_BATCH, n, SIGNAL_BATCH):
        e = min(a + SIGNAL_BATCH, n)
        L[a:e] = signal(g[a:e], t[a:e])
    return L


def _scratch(M: int, K: int = 0) -> tuple[np.ndarray, ...]:
    """Scratch space of :func:`_step` (``K = 0``) or of :func:`_commit_turned` for ``K``
    turns, which allocate nothing themselves (:func:`~eventrecon.sim.jit.njit_borrowing`)."""
    if K:
        return np.empty(M + KEEP + K), np.empty(M + KEEP + K), np.empty(K), np.empty(K)
    return (np.empty(M), np.empty(M), np.empty(M + KEEP), np.empty(M + KEEP),
            np.empty(M + KEEP, np.int64), np.empty((M + KEEP, 3)))


def run_compiled(signal: Callable, pix: np.ndarray, setup, s, stats: dict
                 ) -> tuple[list[tuple[np.ndarray, np.ndarray, np.ndarray]], int]:
    """The ideal-pixel event core, compiled (module docstring).

    Args:
        signal: ``signal(g [N] int64, t [N] float64) -> L [N] float64``.
        pix: ``[P]`` int64 global pixel ids.
        setup: :class:`~eventrecon.sim.core_settings.SignalSetup` without ``lowpass`` and
            ``redraw``.
        s: :class:`~eventrecon.sim.core_settings.CoreSettings`.
        stats: ``n_samples``, ``n_forced``, ``turn_samples`` (added to).

    Returns:
        ``(parts, iterations)``: the events as chunks ``(g, t, p)``, each pixel's in time
        order (not merged across pixels).
    """
    P, M = pix.size, s.block
    L0 = signal(pix, np.zeros(P)) if P else np.zeros(0)
    stats["n_samples"] += P
    st_t, st_L = np.zeros((P, KEEP)), np.repeat(L0[:, None], KEEP, 1)
    h, m = np.full(P, s.max_step), np.full(P, M, np.int64)
    brk, grow = np.zeros(P, bool), np.zeros(P, bool)
    slope, ref = np.full(P, np.nan), L0.copy()
    on = setup.theta_on[pix].astype(np.float64)
    off = setup.theta_off[pix].astype(np.float64)
    Wt, WL = np.empty((P, M + KEEP)), np.empty((P, M + KEEP))   # paths waiting for turns
    wlen, wdone = np.zeros(P, np.int64), np.zeros(P, np.int64)
    K_max = P * (M + 1)                          # at most n_acc turns per path
    tr = (np.empty(K_max, np.int64), np.empty(K_max, np.int64), np.empty(K_max),
          np.empty(K_max))
    parts: list = []                             # full event chunks
    cap = 4 * P + 1024

    def chunk(n: int) -> tuple:                  # a new chunk twice as large, the full
        nonlocal cap                             # one kept as is (a pixel whose events
        if n:                                    # did not fit even an empty chunk just
            parts.append(tuple(x[:n] for x in ev))   # gets the larger one)
        cap *= 2
        return np.empty(cap, np.int64), np.empty(cap), np.empty(cap, np.int8)

    ev, n = (np.empty(cap, np.int64), np.empty(cap), np.empty(cap, np.int8)), 0
    tol = 0.5 * s.turn_tol * s.threshold
    it = 0
    scratch, buffers = _scratch(M), _PlanBuffers(P, M)

    while pix.size:
        it += 1
        G, T, start, n_valid, odd = buffers.plan(pix, st_t[:, -1], h, grow, m, s.max_step)
        L = _in_batches(signal, G, T, buffers.L)
        stats["n_samples"] += T.size
        i, K = 0, 0
        while True:
            i, n, K, n_forced = _step(i, T, start, n_valid, odd, L, pix, st_t, st_L, h, m,
                                      brk, grow, slope, ref, on, off, M, s.threshold,
                                      s.max_log_step, s.min_step, s.max_step, s.max_curvature,
                                      s.turn_tol, Wt, WL, wlen, wdone, *tr, K, *ev, n, *scratch)
            stats["n_forced"] += n_forced
            if i == pix.size:
                break
            ev, n = chunk(n), 0
        if K:                                    # refine the waiting turns
            ti, tc, tsig, tgap = (x[:K].copy() for x in tr)
            tri = np.empty((6, K))
            gather_turns(Wt, WL, ti, tc, tri)
            moved = refine_turns(signal, pix[ti], tsig, tri, tgap, tol, stats)
            a, turned = 0, _scratch(M, K)
            while True:
                a, n = _commit_turned(a, ti, tri[1], tri[4], moved, tgap, Wt, WL, wlen,
                                      wdone, pix, st_t, st_L, ref, on, off, *ev, n, *turned)
                if a == K:
                    break
                ev, n = chunk(n), 0
        running = st_t[:, -1] < 1.0
        n_run = np.count_nonzero(running)
        if n_run == 0 or n_run < DROP * running.size:   # finished pixels cost little
            keep = np.flatnonzero(running)
            pix, st_t, st_L, h, m, brk, grow, slope, ref, on, off = (
                x[keep] for x in (pix, st_t, st_L, h, m, brk, grow, slope, ref, on, off))
    parts.append(tuple(x[:n] for x in ev))
    return parts, it
