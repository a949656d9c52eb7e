"""The per-pixel path of the compiled event core: turns, crossings and their times.

Scalar counterparts, expression for expression, of :mod:`eventrecon.sim.paths` (whose
module docstring states the rules), called per pixel from the loops of
:mod:`eventrecon.sim.compiled_core`: the vertex of the parabola through three samples,
the smooth turns of a path and whether one may reach its next level, emission of a
path's crossings and their times (:mod:`eventrecon.sim.crossing`), and the vertex
refinement of the turns that may reach a level (:func:`refine_turns`, the counterpart of
:func:`eventrecon.sim.paths.refine_turns` for the ideal pixel). The per-event helpers are
inlined at their call sites (a call would cost more than their work).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from eventrecon.sim.crossing import (
    BRACKETED_STEPS,
    CONVERGED,
    FAR,
    FIRST_LEG,
    FIRST_TURN,
    GRID,
    HOLD,
    KEEP,
    NODES,
    QUARTERS,
    SECOND_STEP,
)
from eventrecon.sim.jit import larger, njit, njit_borrowing, njit_inline

__all__ = ["clip", "parabola", "cross_time", "room", "commit_path", "turn", "find_turns",
           "vertex_may_gain", "queue_turns", "gather_turns", "refine_turns"]


@njit_inline
def clip(x, lo, hi):
    """``np.clip`` of a scalar (``NaN`` stays ``NaN``)."""
    if x < lo:
        return lo
    if x > hi:
        return hi
    return x


@njit_inline
def parabola(xa, ya, xb, yb, xc, yc):
    """Vertex ``(x, y)`` and ``A`` of the parabola through three points (scalar form of
    :func:`eventrecon.sim.paths._parabola`)."""
    m1 = (yb - ya) / (xb - xa)
    A = ((yc - yb) / (xc - xb) - m1) / (xc - xa)
    x = clip(0.5 * (xa + xb) - m1 / (2 * A), xa, xc)
    return x, yb + m1 * (x - xb) + A * (x - xb) * (x - xa), A


@njit_inline
def _poly(s, C0, C1, C2, C3, Z0, Z1, Z2):
    """``(ℓ(s), ℓ'(s))`` of the crossing polynomial's Newton form (scalar form of
    :func:`eventrecon.sim.crossing.poly`)."""
    v, dv = C3, 0.0
    dv = v + (s - Z2) * dv
    v = C2 + (s - Z2) * v
    dv = v + (s - Z1) * dv
    v = C1 + (s - Z1) * v
    dv = v + (s - Z0) * dv
    v = C0 + (s - Z0) * v
    ss = s * (s - 1.0)
    return s + ss * v, 1.0 + (2.0 * s - 1.0) * v + ss * dv


@njit
def _scan_root(u, C0, C1, C2, C3, Z0, Z1, Z2):
    """The first root of ``ℓ(s) = u`` on ``[0, 1]``: the first sign change on a grid of
    ``GRID + 1`` points, then Newton steps kept inside that bracket (the rare path of
    :func:`cross_time`, kept out of line)."""
    k = 0
    for j in range(GRID + 1):
        if _poly(j / GRID, C0, C1, C2, C3, Z0, Z1, Z2)[0] - u >= 0:
            k = j
            break
    k = larger(k, 1)
    lo, hi = (k - 1) / GRID, k / GRID
    x = 0.5 * (lo + hi)
    for _ in range(BRACKETED_STEPS):
        qx, dx = _poly(x, C0, C1, C2, C3, Z0, Z1, Z2)
        qx = qx - u
        if qx >= 0:
            hi = x
        else:
            lo = x
        xn = x - qx / dx
        x = xn if (xn > lo) and (xn < hi) else 0.5 * (lo + hi)
    finite = (math.isfinite(C0) and math.isfinite(C1) and math.isfinite(C2)
              and math.isfinite(C3))
    return x if finite else clip(u, 0.0, 1.0)


@njit_inline
def cross_time(pt, pL, c, length, level):
    """Time where the path ``pt, pL`` (``length`` points) meets ``level`` on the leg
    ``c → c+1``: the polynomial through points ``c−2 … c+3`` (those present), Newton
    from the root of its quadratic part (scalar form of :func:`eventrecon.sim.crossing.cross_times`;
    the module docstring there states the rule)."""
    last = length - 1
    x1, y1 = pt[c], pL[c]
    h, D = pt[c + 1] - x1, pL[c + 1] - y1
    ih, iD = 1.0 / h, 1.0 / D
    u = (level - y1) * iD
    z0 = z1 = z2 = z3 = y0 = y1_ = y2 = y3 = 0.0
    cnt = 0
    zl = zr = 0.0                                # the outer node taken on each side
    okl = okr = False
    for k in range(4):                           # nodes c−1, c+2, c−2, c+3
        j, left = c + NODES[k][0], NODES[k][1] < 0
        if j < 0 or j > last or (k >= 2 and not (okl if left else okr)):
            continue
        z, y = (pt[j] - x1) * ih, (pL[j] - y1) * iD
        if left:
            if not z < (0.0 if k == 0 else zl):
                continue
            zl, okl = z, True
        else:
            if not z > (1.0 if k == 1 else zr):
                continue
            zr, okr = z, True
        if cnt == 0:
            z0, y0 = z, y
        elif cnt == 1:
            z1, y1_ = z, y
        elif cnt == 2:
            z2, y2 = z, y
        else:
            z3, y3 = z, y
        cnt += 1
    C0 = C1 = C2 = C3 = Z0 = Z1 = Z2 = 0.0       # the divided differences
    g0 = g1 = g2 = d12 = 0.0
    if cnt >= 1:
        g0 = (y0 - z0) / (z0 * (z0 - 1.0))
        C0, Z0 = g0, z0
    if cnt >= 2:
        g1 = (y1_ - z1) / (z1 * (z1 - 1.0))
        C1, Z1 = (g1 - g0) / (z1 - z0), z1
    if cnt >= 3:
        g2 = (y2 - z2) / (z2 * (z2 - 1.0))
        d12 = (g2 - g1) / (z2 - z1)
        C2, Z2 = (d12 - C1) / (z2 - z0), z2
    if cnt == 4:
        g3 = (y3 - z3) / (z3 * (z3 - 1.0))
        C3 = (((g3 - g2) / (z3 - z2) - d12) / (z3 - z1) - C2) / (z3 - z0)
    b = 1.0 - C0                                 # the quadratic part's root in [0, 1]
    r = math.sqrt(b * b + 4.0 * C0 * u)
    s0 = 2.0 * u / (b + r) if b >= 0 else (r - b) / (2.0 * C0)
    q, d = _poly(s0, C0, C1, C2, C3, Z0, Z1, Z2)
    s = s0 - (q - u) / d
    ok = d > 0
    if abs(s - s0) > SECOND_STEP:                # a second step where the first was long
        q, d = _poly(s, C0, C1, C2, C3, Z0, Z1, Z2)
        s = s - (q - u) / d
        ok = ok and d > 0
    ok = ok and (s >= 0.0) and (s <= 1.0)
    if ok and not abs(s - s0) < FAR:             # two more steps; below u before it
        q2, d2 = _poly(s, C0, C1, C2, C3, Z0, Z1, Z2)
        s3 = s - (q2 - u) / d2
        q3, d3 = _poly(s3, C0, C1, C2, C3, Z0, Z1, Z2)
        s = s3 - (q3 - u) / d3
        ok = ((s >= 0.0) and (s <= 1.0) and (d2 > 0) and (d3 > 0)
              and abs(s - s3) < CONVERGED)
        for a in QUARTERS:
            ok = ok and _poly(a * s, C0, C1, C2, C3, Z0, Z1, Z2)[0] < u
    if not ok:
        s = _scan_root(u, C0, C1, C2, C3, Z0, Z1, Z2)
    return x1 + s * h


@njit
def room(pL, length, th):
    """At most how many crossings a path of ``length`` points emits (``th`` the smaller
    threshold): ``Σ ⌊|ΔL|/th⌋ + 1`` over its legs, bounded by ``Σ |ΔL|/th + legs``."""
    total = 0.0
    for c in range(length - 1):
        total += abs(pL[c + 1] - pL[c])
    return total / th + length + 1             # a float: no integer overflow


@njit_inline
def commit_path(pt, pL, length, done, i, gid, st_t, st_L, ref, on, off, bg, bt, bp, n):
    """Emit the crossings of the legs ``c → c+1``, ``FIRST_LEG ≤ c < length − 1 − HOLD``
    (``< length − 1`` once ``done``), of one pixel's path (the last legs wait for their
    right neighbours unless the path ends) into ``bg, bt, bp`` from ``n`` on (room for
    :func:`room` events is the caller's), time them, update the pixel's reference level
    and keep the last ``KEEP`` points as its state. Returns the new ``n``."""
    r, th_on, th_off = ref[i], on[i], off[i]
    hi, lo = r + th_on, r - th_off
    for c in range(FIRST_LEG, length - 1 - HOLD * (1 - done)):
        Lb = pL[c + 1]
        while Lb >= hi or Lb <= lo:              # ref − θ_off < L < ref + θ_on after
            up = Lb >= hi
            r = hi if up else lo
            bg[n], bt[n], bp[n] = gid, cross_time(pt, pL, c, length, r), 1 if up else -1
            n += 1
            hi, lo = r + th_on, r - th_off
    ref[i] = r
    for k in range(KEEP):
        st_t[i, k], st_L[i, k] = pt[length - KEEP + k], pL[length - KEEP + k]
    return n


@njit_inline
def turn(pt, pL, c, bound, tol_over):
    """The turn at sample ``c`` of a path, if smooth and reaching more than ``tol_over``
    beyond ``L(s_c)`` (the conditions of :func:`eventrecon.sim.paths._turns`):
    ``(keep, sig, x, y, A)``, the last three those of its :func:`parabola`."""
    sig = 1.0 if pL[c] > pL[c - 1] else -1.0
    xa, xb, xc = pt[c - 1], pt[c], pt[c + 1]
    ya, yb, yc = pL[c - 1], pL[c], pL[c + 1]
    xv, yv, A = parabola(xa, ya, xb, yb, xc, yc)
    over = sig * (yv - yb)
    keep = ((xa < xb) and (xb < xc) and (sig * A < 0) and (over > tol_over)
            and (abs(A) * (xc - xa) * (xc - xb) <= 2 * bound))
    return keep, sig, xv, yv, A


@njit_inline
def vertex_may_gain(xa, xb, xc, xv, over, gap, tol):
    """Whether a turn's vertex ``xv`` (reaching ``over`` beyond the middle sample ``xb``)
    is worth evaluating: inside the bracket ``(xa, xc)``, not its middle point, and within
    ``2·over + 2·tol`` of the next level (``gap``)."""
    return (xa < xv) and (xv < xc) and (xv != xb) and (gap <= 2 * over + 2 * tol)


@njit_inline
def find_turns(pt, pL, length, done, cbound, tol, ct, cv):
    """Smooth turns of a path (``_turns`` of the numpy core): where the steps change sign
    at a sample ``FIRST_TURN ≤ c ≤ length − 2`` (and, on a path that ends, before its
    last leg).
    Writes their samples to ``ct`` and ``(sign, x, y)`` to the rows of ``cv``: +1 at a
    peak, then the vertex of the parabola through the turn and its neighbours. Returns
    how many."""
    nt = 0
    last = length - 2 if done and length >= KEEP + 2 else -1   # an ending path's last leg
    for c in range(FIRST_TURN, length - 1):
        prod = (pL[c] - pL[c - 1]) * (pL[c + 1] - pL[c])
        if prod < 0 or (c == last and prod > 0):
            keep, sg, xv, yv, _ = turn(pt, pL, c, cbound, tol)
            if keep:
                ct[nt] = c
                cv[nt, 0], cv[nt, 1], cv[nt, 2] = sg, xv, yv
                nt += 1
    return nt


@njit_inline
def queue_turns(i, pt, pL, nt, ct, cv, r0, th_on, th_off, tol, tr_i, tr_c, tr_sig, tr_gap,
                 n_turns):
    """Whether one of pixel ``i``'s ``nt`` turns (:func:`find_turns`) may reach its next
    level, i.e. the path must wait for refinement; if so its turns are written to ``tr_*``
    from ``n_turns`` on, with the distance from each to its next level (the reference level
    there: emission without timing from ``r0``; ``−inf`` when the path has two turns: both
    are refined)."""
    wait = False
    for j in range(nt):
        c, sg, xv, yv = ct[j], cv[j, 0], cv[j, 1], cv[j, 2]
        gap = -np.inf
        if nt == 1:
            r = r0
            for cc in range(FIRST_LEG, c):
                Lb = pL[cc + 1]
                while Lb >= r + th_on:
                    r += th_on
                while Lb <= r - th_off:
                    r -= th_off
            gap = sg * ((r + th_on if sg > 0 else r - th_off) - pL[c])
        over = sg * (yv - pL[c])                 # sg·A < 0 and over > tol: find_turns
        wait |= vertex_may_gain(pt[c - 1], pt[c], pt[c + 1], xv, over, gap, tol)
        tr_i[n_turns + j], tr_c[n_turns + j] = i, c
        tr_sig[n_turns + j], tr_gap[n_turns + j] = sg, gap
    return wait


@njit_borrowing
def gather_turns(Wt, WL, ti, tc, tri):
    """``tri [6, K]``: rows ``x_{c−1}, x_c, x_{c+1}, L_{c−1}, L_c, L_{c+1}`` of the waiting
    paths ``Wt, WL`` at turn ``k``'s pixel ``ti[k]`` and sample ``tc[k]``."""
    for k in range(ti.size):
        i, c = ti[k], tc[k]
        for o in range(3):
            tri[o, k], tri[3 + o, k] = Wt[i, c - 1 + o], WL[i, c - 1 + o]


@njit_borrowing
def _vertices(tri, sig, gap, need, tol, q, x):
    """The turns ``need`` whose parabola's vertex may still gain: inside its bracket, not
    its middle point, beyond it by more than ``tol`` and within ``2·over + 2·tol`` of the
    next level (``gap``). Writes their indices to ``q`` and vertices to ``x``; returns
    how many."""
    n = 0
    for k in range(need.size):
        if need[k]:
            xa, xb, xc = tri[0, k], tri[1, k], tri[2, k]
            xv, yv, A = parabola(xa, tri[3, k], xb, tri[4, k], xc, tri[5, k])
            over = sig[k] * (yv - tri[4, k])
            if (sig[k] * A < 0) and (over > tol) and vertex_may_gain(xa, xb, xc, xv, over,
                                                                    gap[k], tol):
                q[n], x[n] = k, xv
                n += 1
    return n


@njit_inline
def _keep_bracketed(tri, row, k, val, better, right):
    """Rows ``row … row + 2`` of turn ``k``: the new value ``val`` becomes the middle if
    ``better`` (the old middle moving to the side it left), else the bracket's side."""
    old = tri[row + 1, k]
    if better:
        tri[row + 1, k] = val
        if right:
            tri[row, k] = old
        else:
            tri[row + 2, k] = old
    elif right:
        tri[row + 2, k] = val
    else:
        tri[row, k] = val


@njit_borrowing
def _bracket(tri, sig, gap, need, q, x, y, n):
    """Keep the best point of each refined turn ``q[j]`` in the middle of its bracket,
    the new sample ``(x[j], y[j])`` on the side it fell; only those go on (``need``)."""
    for k in range(need.size):
        need[k] = False
    for j in range(n):
        k = q[j]
        right = x[j] > tri[1, k]
        better = sig[k] * (y[j] - tri[4, k]) > 0
        if better:
            gap[k] -= sig[k] * (y[j] - tri[4, k])
        _keep_bracketed(tri, 0, k, x[j], better, right)
        _keep_bracketed(tri, 3, k, y[j], better, right)
        need[k] = True


def refine_turns(signal: Callable, g: np.ndarray, sig: np.ndarray, tri: np.ndarray,
                 gap: np.ndarray, tol: float, stats: dict) -> np.ndarray:
    """Successive parabolic interpolation of an ideal pixel's turns, two rounds at most,
    in place on ``tri [6, K]`` (:func:`gather_turns`; its middle point stays the best);
    ``g [K]`` the turns' pixels, ``sig [K]`` +1 at a peak, ``gap [K]`` the distance to the
    next level (updated). The same rule and expressions as
    :func:`eventrecon.sim.paths.refine_turns`, so both engines give the same points.

    Returns the mask of turns whose best point moved."""
    K = sig.size
    x0, need = tri[1].copy(), np.ones(K, np.bool_)
    q, x = np.empty(K, np.int64), np.empty(K)
    for _ in range(2):
        n = _vertices(tri, sig, gap, need, tol, q, x)
        if not n:
            break
        y = signal(g[q[:n]], x[:n])
        stats["n_samples"] += n
        stats["turn_samples"] += n
        _bracket(tri, sig, gap, need, q, x, y, n)
    return tri[1] != x0
