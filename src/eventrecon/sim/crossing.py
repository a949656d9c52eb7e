"""Crossing times of the event core: where a pixel's sampled path meets a level.

A crossing of ``level`` on the leg ``c → c+1`` of a path ``(t_k, L_k)`` is timed on the
interpolating polynomial through the leg and up to two neighbours on each side, the
points ``c−2 … c+3`` (a quintic; lower order where the path starts, ends or repeats a
point). In the leg's own coordinates ``s = (t − t_c)/h``, ``h = t_{c+1} − t_c``, and
``ℓ = (L − L_c)/(L_{c+1} − L_c)``, the leg's ends are ``(0, 0)`` and ``(1, 1)`` and the
polynomial has the Newton form

    ``ℓ(s) = s + s(s−1)·(C_0 + (s−z_0)(C_1 + (s−z_1)(C_2 + (s−z_2)·C_3)))``,

``z_0, z_1, …`` the outer nodes in the order ``c−1, c+2, c−2, c+3`` (those present), and
``C_k = ℓ[0, 1, z_0, …, z_k]`` the divided differences, from ``ℓ[0, 1, z] = (y − z) /
(z(z − 1))`` at each node ``(z, y)``. A node is present when it lies strictly outside
the nodes already taken on its side (``z < 0`` left, ``z > 1`` right, and beyond the first
one); a point beyond the path's end is not a node.

The root of ``ℓ(s) = u``, ``u = (level − L_c)/(L_{c+1} − L_c)``, starts from the root in
``[0, 1]`` of the quadratic part ``s + C_0·s(s−1) = u`` (closed form; ``u`` itself with no
outer node) and takes a Newton step, and a second where the first moved it by more than
``1e-2`` (about a sixth of the crossings on the benchmark's grating); kept where it stays in
``[0, 1]`` on positive slopes within 0.1 of the start. Where it lands farther (a strongly
curved leg), two more steps follow, kept where the slopes stay positive, the last step
moved it by less than ``1e-3`` and the polynomial lies below ``u`` at a quarter, half and
three quarters of the root (it is then the leg's first root but for a wiggle between
those points). Elsewhere (the polynomial may not be monotone on the leg) the first root
on the leg is taken: the first sign change on a grid of 33 points, then six Newton steps
kept inside that bracket (a bisection where a step would leave it); a polynomial with a
non-finite coefficient gives the straight-leg time.

The core keeps five points of a pixel's path between iterations and holds back its last
two legs (:data:`KEEP`, :data:`HOLD`), so every leg but a path's first two and last two
has both its neighbours a side when it is timed.

The interpolation error of the time falls as ``h⁶`` (a cubic through ``c−1 … c+2``:
``h⁴``). :func:`cross_times` times a batch of crossings at once, each on its own leg.
"""

from __future__ import annotations

import numpy as np

__all__ = ["cross_times", "newton_form", "first_root", "poly"]

#: Outer nodes in the order they enter the Newton form: offsets from the leg's start
#: ``c`` and their side (``-1`` left, ``+1`` right).
NODES = ((-1, -1), (2, 1), (-2, -1), (3, 1))
#: Points of a pixel's path the core keeps between iterations, and the legs it holds back:
#: a leg is emitted once its two right neighbours are sampled, and the
#: first leg of the next path still has its two left ones. In a path of the kept points
#: and new samples the legs ``FIRST_LEG … length − 2 − HOLD`` are emitted (all to the end
#: once the path reaches ``t = 1``), and the turns at samples ``FIRST_TURN … length − 2``
#: are new (their right neighbour arrived).
KEEP, HOLD = 5, 2
FIRST_LEG, FIRST_TURN = KEEP - 1 - HOLD, KEEP - 1
#: A second Newton step is taken where the first moved the root by more than this
#: (Newton's error after a step of ``δ`` is about ``δ²·ℓ''/2ℓ'``).
SECOND_STEP = 1e-2
#: A root farther than this from the quadratic part's (a strongly curved leg) takes two
#: more steps, and is the leg's first when the polynomial is below the level at these
#: fractions of it ...
FAR, QUARTERS = 0.1, (0.25, 0.5, 0.75)
#: ... and when the last of those steps moved it by less than this.
CONVERGED = 1e-3
#: Otherwise the first sign change on a grid of ``GRID + 1`` points brackets the first
#: root, and Newton steps stay inside that bracket (a bisection where one would leave it).
GRID, BRACKETED_STEPS = 32, 6


def poly(s: np.ndarray, C: np.ndarray, Z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(ℓ(s), ℓ'(s))`` of the Newton form (module docstring) with coefficients
    ``C [4, …]`` and centres ``Z [3, …]`` (absent ones zero), broadcast against ``s``."""
    shape = np.broadcast(s, C[3]).shape
    v, dv = np.broadcast_to(C[3], shape), np.zeros(shape)
    for k in (2, 1, 0):
        dv = v + (s - Z[k]) * dv
        v = C[k] + (s - Z[k]) * v
    ss = s * (s - 1.0)
    return s + ss * v, 1.0 + (2.0 * s - 1.0) * v + ss * dv


def newton_form(Pt: np.ndarray, PL: np.ndarray, c: np.ndarray, i: np.ndarray,
                length: np.ndarray) -> tuple[np.ndarray, ...]:
    """The crossing polynomials of the legs ``c → c+1`` of columns ``i`` (``[E]`` each)
    of the paths ``Pt, PL`` (``[C, n]``, ``length [n]`` points each): ``(x1, h, y1, D,
    C [4, E], Z [3, E])``, the leg's start and extent in ``t`` and ``L`` and the Newton
    form's coefficients and centres (module docstring; absent ones zero)."""
    n = Pt.shape[1]
    Tf, Lf = Pt.ravel(), PL.ravel()
    f, last = c * n + i, length[i] - 1
    x1, y1 = Tf[f], Lf[f]
    h, D = Tf[f + n] - x1, Lf[f + n] - y1
    E = c.size
    z_raw, y_raw, ok = np.zeros((4, E)), np.zeros((4, E)), np.zeros((4, E), bool)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ih, iD = 1.0 / h, 1.0 / D
        for k, (off, side) in enumerate(NODES):
            j = c + off
            g = np.clip(j, 0, last) * n + i
            z_raw[k], y_raw[k] = (Tf[g] - x1) * ih, (Lf[g] - y1) * iD
            inner = 0.0 if side < 0 else 1.0
            if k >= 2:                           # beyond the first node on its side
                inner = np.where(ok[k - 2], z_raw[k - 2], np.nan)
            ok[k] = (j >= 0) & (j <= last) & (side * (z_raw[k] - inner) > 0)
        slot = np.cumsum(ok, 0) - 1              # the present nodes first, in order
        z, y = np.zeros((4, E)), np.zeros((4, E))
        for k in range(4):
            e = np.flatnonzero(ok[k])
            z[slot[k, e], e], y[slot[k, e], e] = z_raw[k, e], y_raw[k, e]
        count = ok.sum(0)
        # divided differences: g_k = ℓ[0, 1, z_k], then the table's diagonal
        gk = (y - z) / (z * (z - 1.0))
        d12 = (gk[2] - gk[1]) / (z[2] - z[1])
        C = np.zeros((4, E))
        C[0] = gk[0]
        C[1] = (gk[1] - gk[0]) / (z[1] - z[0])
        C[2] = (d12 - C[1]) / (z[2] - z[0])
        C[3] = (((gk[3] - gk[2]) / (z[3] - z[2]) - d12) / (z[3] - z[1]) - C[2]) / (z[3] - z[0])
        C[np.arange(4)[:, None] >= count] = 0.0
        Z = np.where(np.arange(3)[:, None] < count, z[:3], 0.0)
    return x1, h, y1, D, C, Z


def first_root(u: np.ndarray, C: np.ndarray, Z: np.ndarray) -> np.ndarray:
    """``s [E]`` in ``[0, 1]`` with ``ℓ(s) = u`` for the Newton forms ``C, Z`` (module
    docstring): Newton from the root of the quadratic part, or the first root on the leg."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        b = 1.0 - C[0]                           # s + C_0·s(s−1) = u, its root in [0, 1]
        r = np.sqrt(b * b + 4.0 * C[0] * u)      # (the form without cancellation)
        s0 = np.where(b >= 0, 2.0 * u / (b + r), (r - b) / (2.0 * C[0]))
        q, d = poly(s0, C, Z)
        s = s0 - (q - u) / d
        ok = d > 0
        again = np.flatnonzero(np.abs(s - s0) > SECOND_STEP)
        if again.size:                           # a second step where the first was long
            q, d = poly(s[again], C[:, again], Z[:, again])
            s[again] = s[again] - (q - u[again]) / d
            ok[again] &= d > 0
        ok &= (s >= 0.0) & (s <= 1.0)
        far = np.flatnonzero(ok & ~(np.abs(s - s0) < FAR))
        if far.size:                             # two more steps; below u before it
            Cf, Zf, uf = C[:, far], Z[:, far], u[far]
            q2, d2 = poly(s[far], Cf, Zf)
            s3 = s[far] - (q2 - uf) / d2
            q3, d3 = poly(s3, Cf, Zf)
            s4 = s3 - (q3 - uf) / d3
            good = ((s4 >= 0.0) & (s4 <= 1.0) & (d2 > 0) & (d3 > 0)
                    & (np.abs(s4 - s3) < CONVERGED))
            for a in QUARTERS:
                good &= poly(a * s4, Cf, Zf)[0] < uf
            s[far], ok[far] = s4, good
        bad = np.flatnonzero(~ok)
        if bad.size:                             # the first root on the leg: the first
            Cb, Zb, ub = C[:, bad], Z[:, bad], u[bad]   # sign change on a grid, then
            grid = np.arange(GRID + 1.0)[:, None] / GRID   # Newton kept in the bracket
            k = np.maximum(np.argmax(poly(grid, Cb, Zb)[0] - ub >= 0, axis=0), 1)
            lo, hi = (k - 1) / GRID, k / GRID
            x = 0.5 * (lo + hi)
            for _ in range(BRACKETED_STEPS):
                qx, dx = poly(x, Cb, Zb)
                qx = qx - ub
                lo, hi = np.where(qx >= 0, lo, x), np.where(qx >= 0, x, hi)
                xn = x - qx / dx
                x = np.where((xn > lo) & (xn < hi), xn, 0.5 * (lo + hi))
            s[bad] = np.where(np.isfinite(Cb).all(0), x, np.clip(ub, 0.0, 1.0))
    return s


def cross_times(Pt: np.ndarray, PL: np.ndarray, c: np.ndarray, i: np.ndarray,
                level: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Times where paths ``Pt, PL`` (``[C, n]``) meet ``level`` on the legs ``c → c+1``
    of columns ``i`` (``[E]`` each), ``length [n]`` the points of each path (module
    docstring).

    >>> t = np.arange(6.0)[:, None]                 # L = t³ + t, level 4.875 at t = 1.5
    >>> x = cross_times(t, t ** 3 + t, np.array([1]), np.array([0]), np.array([4.875]),
    ...                 np.array([6]))
    >>> round(float(x[0]), 5)                       # the straight leg gives 1.359375
    1.5
    """
    x1, h, y1, D, C, Z = newton_form(Pt, PL, c, i, length)
    with np.errstate(divide="ignore", invalid="ignore"):
        u = (level - y1) * (1.0 / D)
    return x1 + first_root(u, C, Z) * h
