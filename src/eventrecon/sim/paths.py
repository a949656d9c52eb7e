"""Sampled log-signal paths of the event core: turns, crossings and their times.

Each running pixel of :func:`~eventrecon.sim.ideal.run_core` keeps a *path*: its samples
``(t, L)`` joined by straight legs. :func:`commit` appends a block of accepted samples
to the paths of many pixels at once (laid out ``[sample, pixel]``) and

1. emits the crossings of every leg but the last ``HOLD`` (they wait for their two right
   neighbours; :data:`~eventrecon.sim.crossing.KEEP`): while a leg reaches
   ``L ≥ r + θ_on`` an ON event fires and ``r ← r + θ_on`` (OFF alike), leg by leg, in
   path order, noting ``r`` at each sample;
2. refines the *turns*: where the steps of ``L`` change sign at a sample ``s_k``, the
   parabola through ``s_{k−1}, s_k, s_{k+1}`` puts the extremum more than
   ``turn_tol·θ/2`` beyond ``L(s_k)`` and the next level (``r ± θ`` at ``s_k``) lies
   within twice that distance, the signal is evaluated at the vertex (successive
   parabolic interpolation, two rounds). If the best point reaches the level, it joins
   the path between its neighbours and the pixel's block is emitted again: a level the
   true extremum passes by more than about ``turn_tol·θ`` is never lost;
3. times each crossing: the root on ``[t_a, t_b]`` of ``p(t) = level`` for the
   polynomial ``p`` through the leg's samples and up to two outer neighbours on each side
   (a quintic; lower order where the path has fewer), a Newton step from the root of
   its quadratic part; where ``p`` is not monotone there, its first root on the leg
   (:mod:`~eventrecon.sim.crossing`).

Turns are only refined where they are smooth: a second difference beyond twice the
sampling bound marks a jump, whose crossings the path already stamps at the jump. With
re-drawn thresholds (``threshold_noise``) the next level is not known ahead, and every
smooth turn is refined before emission.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from eventrecon.sim.core_settings import CoreSettings, SignalSetup
from eventrecon.sim.crossing import FIRST_LEG, FIRST_TURN, HOLD, KEEP, cross_times

__all__ = ["PathState", "commit", "cross_times", "refine_turns"]


class PathState:
    """Per running pixel: global id, row of ``busy``, the last ``KEEP`` path points
    ``s_{−4} … s_0`` (``t, Lf, Lr [KEEP, P]``, :data:`eventrecon.sim.crossing.KEEP`; the
    legs ``s_{−2} → s_{−1} → s_0`` are not emitted yet), step ``h``, block length ``m``,
    bisection / growth flags, last slope (NaN: unknown), reference level and thresholds
    (see :func:`~eventrecon.sim.ideal.run_core`)."""

    FIELDS = ("pix", "row", "t", "Lf", "Lr", "h", "m", "brk", "grow", "slope", "ref", "on",
              "off")

    def __init__(self, pix: np.ndarray, L0: np.ndarray, setup: SignalSetup, s: CoreSettings,
                 busy: np.ndarray | None):
        P = pix.size
        self.pix, self.row, self.t, self.busy = pix, np.arange(P), np.zeros((KEEP, P)), busy
        self.Lf = np.repeat(L0[None], KEEP, 0)
        self.Lr = self.Lf if setup.lowpass is None else self.Lf.copy()  # no filter: one array
        self.h, self.m = np.full(P, s.max_step), np.full(P, s.block)
        self.brk, self.grow = np.zeros(P, bool), np.zeros(P, bool)
        self.slope, self.ref = np.full(P, np.nan), L0.copy()
        self.on = setup.theta_on[pix].astype(np.float64)
        self.off = setup.theta_off[pix].astype(np.float64)

    def keep(self, mask: np.ndarray) -> None:
        """Drop the pixels outside ``mask`` (finished) from every array."""
        alias = self.Lr is self.Lf
        for f in self.FIELDS:
            v = getattr(self, f)
            if not (alias and f == "Lr"):
                setattr(self, f, v[mask] if v.ndim == 1 else v.compress(mask, 1))
        if alias:
            self.Lr = self.Lf


def _parabola(xa, ya, xb, yb, xc, yc) -> tuple:
    """Vertex ``(x, y)`` and ``A`` (half the second derivative) of the parabola through
    ``(xa, ya), (xb, yb), (xc, yc)``, ``xa < xb < xc`` (arrays); ``x`` clipped to
    ``[xa, xc]``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        m1 = (yb - ya) / (xb - xa)
        A = ((yc - yb) / (xc - xb) - m1) / (xc - xa)
        x = np.clip(0.5 * (xa + xb) - m1 / (2 * A), xa, xc)
        return x, yb + m1 * (x - xb) + A * (x - xb) * (x - xa), A


def _turns(P: list, D: np.ndarray, length: np.ndarray, done: np.ndarray,
           s: CoreSettings) -> tuple:
    """Smooth turns of the paths ``P = [t, Lf, Lr]`` (``[C, n]``) at samples
    ``FIRST_TURN ≤ c ≤ length − 2`` (sign change of the steps: ``D`` are the legs from
    column ``FIRST_TURN`` on; on a path that ends (``done``) also before its last leg,
    where a turn has no later sample to show it) whose parabola reaches more than
    ``turn_tol·θ/2`` beyond.

    Returns ``(c, i, sig, tri)``: ``sig`` +1 at a peak, ``tri`` the three points
    ``[[ta, tb, tc], [La, Lb, Lc], [ra, rb, rc]]``.
    """
    n = D.shape[1]
    first = (P[1][FIRST_TURN] - P[1][FIRST_TURN - 1]) * D[0] < 0
    j, i = np.divmod(np.flatnonzero(first), n)
    j2, i2 = np.divmod(np.flatnonzero(D[:-1] * D[1:] < 0), n)
    c, i = np.concatenate([j + FIRST_TURN, j2 + KEEP]), np.concatenate([i, i2])
    ok = c <= length[i] - 2
    c, i = c[ok], i[ok]
    end = np.flatnonzero(done & (length >= KEEP + 2))
    if end.size:                             # the last leg of an ending path
        ce = length[end] - 2
        Q = P[1]
        same = (Q[ce, end] - Q[ce - 1, end]) * (Q[ce + 1, end] - Q[ce, end]) > 0
        c, i = np.concatenate([c, ce[same]]), np.concatenate([i, end[same]])
    sig = np.where(P[1][c, i] > P[1][c - 1, i], 1.0, -1.0)
    tri = [[Q[c + o, i] for o in (-1, 0, 1)] for Q in P]
    (xa, xb, xc), (ya, yb, yc) = tri[0], tri[1]
    _, yv, A = _parabola(xa, ya, xb, yb, xc, yc)
    over = sig * (yv - yb)
    bound = s.max_curvature * s.max_log_step * s.threshold
    keep = ((xa < xb) & (xb < xc) & (sig * A < 0) & (over > 0.5 * s.turn_tol * s.threshold)
            & (np.abs(A) * (xc - xa) * (xc - xb) <= 2 * bound))   # smooth, not a jump
    keep = np.flatnonzero(keep)
    return c[keep], i[keep], sig[keep], [[q[keep] for q in Q] for Q in tri]


def refine_turns(signal: Callable, g: np.ndarray, sig: np.ndarray, tri: list,
                 need: np.ndarray, gap: np.ndarray | None, setup: SignalSetup, tol: float,
                 stats: dict) -> np.ndarray:
    """Successive parabolic interpolation of the turns ``need`` (two rounds at most),
    in place on ``tri`` (its middle point stays the best); ``gap`` (or ``None``: always)
    the distance to the next level: only turns that may reach it go on.

    Returns the mask of turns whose best point moved."""
    x0 = tri[0][1].copy()
    for _ in range(2):
        (xa, xb, xc), (ya, yb, yc) = tri[0], tri[1]
        xv, yv, A = _parabola(xa[need], ya[need], xb[need], yb[need], xc[need], yc[need])
        q = np.flatnonzero(need)
        over = sig[q] * (yv - yb[q])
        go = (sig[q] * A < 0) & (over > tol) & (xa[q] < xv) & (xv < xc[q]) & (xv != xb[q])
        if gap is not None:
            go &= gap[q] <= 2 * over + 2 * tol
        q, x = q[go], xv[go]
        if not q.size:
            break
        r = signal(g[q], x)
        stats["n_samples"] += q.size
        stats["turn_samples"] += q.size
        right = x > xb[q]
        y = r
        if setup.lowpass is not None:
            side = [np.where(right, Q[1][q], Q[0][q]) for Q in tri]
            y = setup.lowpass(side[1], side[2], r, x - side[0])
        better = sig[q] * (y - yb[q]) > 0
        if gap is not None:
            gap[q] -= np.where(better, sig[q] * (y - yb[q]), 0.0)
        for (qa, qb, qc), val in zip(tri, (x, y, r)):   # keep the best point bracketed
            old = qb[q]
            qa[q] = np.where(better & right, old, np.where(~better & ~right, val, qa[q]))
            qc[q] = np.where(better & ~right, old, np.where(~better & right, val, qc[q]))
            qb[q] = np.where(better, val, old)
        need = np.zeros_like(need)
        need[q] = True
    return tri[0][1] != x0


def _emit(st: PathState, ids: np.ndarray, hot: np.ndarray, PL: np.ndarray, stop: np.ndarray,
          redraw: Callable | None, snap: bool) -> tuple:
    """Crossings of the legs ``c → c+1``, ``FIRST_LEG ≤ c < stop``, of the paths ``PL`` of the
    columns ``hot`` (pixels ``ids[hot]``), leg by leg; updates their reference level.

    Returns ``((c, column, level, up), snapshot)``; the snapshot (if ``snap``) holds the
    reference level at each sample ``[C, len(hot)]``, in the order of ``hot``."""
    C = PL.shape[0]
    order = np.argsort((C - stop[hot]).astype(np.uint8), kind="stable")  # live rows: a prefix
    hot = hot[order]
    live = np.cumsum(np.bincount(stop[hot], minlength=C + 1)[::-1])[::-1]
    LT, r, on, off = PL.take(hot, 1), st.ref[ids[hot]], st.on[ids[hot]], st.off[ids[hot]]
    hi, lo, g = r + on, r - off, st.pix[ids[hot]]
    Rs = np.empty((C, hot.size)) if snap else None
    rec: list = []
    for c in range(FIRST_LEG, C - 1):
        if snap:
            Rs[c] = r
        m = live[c + 1]
        if not m:
            break
        Lb = LT[c + 1, :m]
        # ref − θ_off < L < ref + θ_on holds at every point already emitted
        cand = np.flatnonzero((Lb >= hi[:m]) | (Lb <= lo[:m]))
        while cand.size:
            b = Lb[cand]
            up = b >= hi[cand]
            level = np.where(up, hi[cand], lo[cand])
            rec.append((np.full(cand.size, c), hot[cand], level, up))
            r[cand] = level
            if redraw is not None:
                on[cand], off[cand] = redraw(g[cand])
            hi[cand], lo[cand] = level + on[cand], level - off[cand]
            cand = cand[np.where(up, b >= hi[cand], b <= lo[cand])]
    st.ref[ids[hot]], st.on[ids[hot]], st.off[ids[hot]] = r, on, off
    if snap:
        Rs[c:] = r
        Rs = Rs[:, np.argsort(order)]                      # back to the order of ``hot``
    return rec, Rs


def _walk_held(r: np.ndarray, PL: np.ndarray, i: np.ndarray, a: np.ndarray, c: np.ndarray,
               on: np.ndarray, off: np.ndarray) -> np.ndarray:
    """The reference levels ``r [K]`` of the columns ``i`` of the paths ``PL`` at samples
    ``a`` carried on to the samples ``c ≥ a`` over the held-back legs between (at most
    ``HOLD``), level by level as emission would, emitting nothing."""
    r = r.copy()
    for k in range(HOLD):
        act = np.flatnonzero(a + k < c)
        if not act.size:
            break
        Lb, ra = PL[a[act] + k + 1, i[act]], r[act]
        while (up := Lb >= ra + on[act]).any():
            ra = np.where(up, ra + on[act], ra)
        while (dn := Lb <= ra - off[act]).any():
            ra = np.where(dn, ra - off[act], ra)
        r[act] = ra
    return r


def _stop(length: np.ndarray, done: np.ndarray) -> np.ndarray:
    """End (exclusive) of the legs a path of ``length`` points emits: all but the last
    ``HOLD``, all of them once it reaches ``t = 1`` (``done``)."""
    return length - 1 - HOLD * (1 - done.astype(np.int64))


def _insert(P: list, length: np.ndarray, col: np.ndarray, pts: list) -> tuple:
    """The paths ``P`` (``[C, n]``) of the columns ``col`` with the points ``pts``
    (``[t, Lf, Lr]``) merged in time order: ``(cols, P', length')``."""
    cols, inv, cnt = np.unique(col, return_inverse=True, return_counts=True)
    o = np.argsort(inv, kind="stable")
    slot = np.empty(col.size, np.int64)
    slot[o] = np.arange(col.size) - (np.cumsum(cnt) - cnt)[inv[o]]
    ext = []
    for Q, v in zip(P, pts):
        e = np.full((int(cnt.max()), cols.size), np.inf)
        e[slot, inv] = v
        ext.append(np.concatenate([Q.take(cols, 1), e]))
    o = np.argsort(ext[0], axis=0, kind="stable")
    n = length[cols] + cnt
    idx = np.take_along_axis(o, np.minimum(np.arange(o.shape[0])[:, None], n - 1), axis=0)
    return cols, [np.ascontiguousarray(np.take_along_axis(Q, idx, axis=0)) for Q in ext], n


def _finish(st: PathState, ids: np.ndarray, P: list, length: np.ndarray, events: list,
            out: list) -> None:
    """Time the ``events`` of the paths ``P`` of pixels ``ids`` into ``out``; keep each
    path's last ``KEEP`` points as the state."""
    if events:
        ec, ei, level, up = (np.concatenate([x[j] for x in events]) for j in range(4))
        t = cross_times(P[0], P[1], ec, ei, level, length)
        out.append((st.pix[ids[ei]], t, np.where(up, 1, -1).astype(np.int8)))
    n = ids.size
    last = (length - 1) * n + np.arange(n)
    for S, Q in zip((st.t, st.Lf, st.Lr) if st.Lr is not st.Lf else (st.t, st.Lf), P):
        Qf = Q.ravel()
        S[:, ids] = np.stack([Qf[last - (KEEP - 1 - k) * n] for k in range(KEEP)])


def commit(signal: Callable, st: PathState, sel, T: np.ndarray, Lr: np.ndarray,
           Lf: np.ndarray, D: np.ndarray, n_acc: np.ndarray, setup: SignalSetup,
           s: CoreSettings, stats: dict, out: list, rec: list | None) -> None:
    """Append the first ``n_acc`` samples of the blocks ``T, Lr, Lf`` (``[M, N]``, steps
    ``D`` of ``Lf``; rows beyond are later samples, not part of the paths) to
    the paths of the pixels ``sel``, emit and refine (module docstring), append the
    events ``(g, t, p)`` to ``out`` and keep each path's last ``KEEP`` points."""
    ids = np.arange(st.pix.size)[sel]
    if n_acc.min() < 1:
        keep = n_acc > 0
        ids, n_acc = ids[keep], n_acc[keep]
        T, Lr, Lf, D = (x.compress(keep, 1) for x in (T, Lr, Lf, D))
        sel = ids
        if not ids.size:
            return
    M, n = T.shape
    pick = (lambda a: a[:, sel]) if isinstance(sel, slice) else (lambda a: a.take(sel, 1))
    P = [np.concatenate([pick(old), new, new[-1:]]) for old, new in ((st.t, T), (st.Lf, Lf))]
    P.append(P[1] if st.Lr is st.Lf else np.concatenate([pick(st.Lr), Lr, Lr[-1:]]))
    length = n_acc + KEEP
    if rec is not None:
        kept = np.arange(M)[:, None] < n_acc
        rec.append((np.broadcast_to(st.pix[ids], (M, n))[kept], T[kept], Lf[kept]))
    ref0, on0, off0 = st.ref[ids], st.on[ids], st.off[ids]
    hot = ((P[1][FIRST_LEG + 1:].max(0) >= ref0 + on0)
           | (P[1][FIRST_LEG + 1:].min(0) <= ref0 - off0))
    done = P[0][length - 1, np.arange(n)] >= 1.0
    c, i, sig, tri = _turns(P, D, length, done, s)
    tol = 0.5 * s.turn_tol * s.threshold
    redo = i[:0]
    if setup.redraw is not None and c.size:      # levels unknown ahead: refine every turn
        moved = refine_turns(signal, st.pix[ids[i]], sig, tri, np.ones(c.size, bool), None,
                             setup, tol, stats)
        redo = np.unique(i[moved])
        hot[redo] = False
    stop = _stop(length, done)
    events, Rs = _emit(st, ids, np.flatnonzero(hot), P[1], stop, setup.redraw,
                       setup.redraw is None and c.size > 0)
    if setup.redraw is None and c.size:          # refine the turns that may reach a level
        pos = np.cumsum(hot) - 1
        r_at = np.where(hot[i], Rs[c, pos[i]] if hot.any() else 0.0, ref0[i])
        r_at = _walk_held(r_at, P[1], i, stop[i], c, on0[i], off0[i])
        gap = sig * (np.where(sig > 0, r_at + on0[i], r_at - off0[i]) - tri[1][1])
        gap[np.bincount(i, minlength=n)[i] > 1] = -np.inf     # two turns: refine both
        moved = refine_turns(signal, st.pix[ids[i]], sig, tri, np.ones(c.size, bool), gap,
                             setup, tol, stats)
        redo = np.unique(i[moved & (gap <= 0)])  # those gained a crossing: emit them again
        if redo.size:
            drop = np.zeros(n, bool)
            drop[redo] = True
            events = [(a[k], b[k], lv[k], u[k]) for a, b, lv, u in events
                      if (k := ~drop[b]).any()]
            st.ref[ids[redo]], st.on[ids[redo]], st.off[ids[redo]] = (
                ref0[redo], on0[redo], off0[redo])
    if redo.size:                                # their paths with the refined points
        m = moved & np.isin(i, redo)
        if rec is not None:
            rec.append((st.pix[ids[i[m]]], tri[0][1][m], tri[1][1][m]))
        cols, Pv, nv = _insert(P, length, i[m], [q[1][m] for q in tri])
        ev_v = _emit(st, ids[cols], np.arange(cols.size), Pv[1], _stop(nv, done[cols]),
                     setup.redraw, False)[0]
        _finish(st, ids, P, length, events, out)     # the state of ``cols`` is replaced:
        _finish(st, ids[cols], Pv, nv, ev_v, out)
    else:
        _finish(st, ids, P, length, events, out)
