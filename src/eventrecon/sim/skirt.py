"""A non-rigidly deforming primitive with exact ray intersection: the ``skirt``.

The skirt is an open, two-sided sheet around the local y axis (world up is −y, so the
rings go from the top, ``y_0``, down to the hem, ``y_{n−1}``), lofted through ``n ≥ 2``
horizontal rings. Ring ``j`` sits at the fixed local height ``y_j`` and, at normalised
time ``t``, is the ellipse ``{c_j(t) + s_j(t)\\,E(t)\\,u(α)}`` in the ``(x, z)`` plane,
``u(α) = (\\sin α, \\cos α)``, ``v_j = (y_j − y_0)/(y_{n−1} − y_0)``:

.. math::
   c_j(t) = A_s v_j^2\\,(\\sin ψ_j, \\cos ψ_j),\\quad ψ_j = φ_s + 2π k_s t − ℓ\\,v_j
   \\qquad\\text{(sway: the hem swings round, lagging the top)}

   s_j(t) = r_j\\big(1 + A_f v_j\\,\\tfrac{1 − \\cos 2π k_f t}{2}\\big)
   \\qquad\\text{(flare: the lower rings open and close)}

   E(t) = Q(β)\\,\\mathrm{diag}(1 + A_q, 1 − A_q)\\,Q(β)^T,\\ β = 2π k_q t
   \\qquad\\text{(squash: an ellipse turning round the skirt)}

with ``Q(β)`` the 2-D rotation. Between rings ``j`` and ``j+1`` (band ``j``,
``λ = (y − y_j)/(y_{j+1} − y_j) ∈ [0, 1]``) the sheet joins equal material angles ``α``
by straight lines; since every ring shares ``E(t)`` the band is the quadric

.. math:: G(x) = |M(q − c(λ))|^2 − s(λ)^2 = 0,\\qquad M = E^{-1},\\
          c(λ) = c_j + λΔc_j,\\ s(λ) = s_j + λΔs_j,

``q = (x, z)``. Along a ray ``x = o + τd`` (local frame) ``λ = λ_0 + λ_1 τ`` is linear,
``q − c(λ) = u + τw`` with ``u = q_o − c_j − λ_0Δc``, ``w = q_d − λ_1Δc``, and
``s(λ) = σ_0 + σ_1 τ``, so the hit solves a quadratic **exactly**:

.. math:: aτ^2 + 2bτ + c = 0,\\quad a = |Mw|^2 − σ_1^2,\\ b = (Mu)·(Mw) − σ_0σ_1,\\
          c = |Mu|^2 − σ_0^2,

keeping roots with ``τ > 0`` and ``λ ∈ [0, 1]`` (the nearest over all bands). The
normal is ``∇G`` (``∂G/∂q = 2M^2(q − c)``, ``∂G/∂y = −2[(M(q−c))·(MΔc) + sΔs]/Δy``),
turned towards the viewer. Textures are evaluated at the *material* point
``(r(λ)\\sin α, y, r(λ)\\cos α)`` of the rest shape (``r(λ)`` the interpolated rest
radius, ``u(α) = M(q − c)/s``), so they stretch and travel with the cloth.

Fields of a ``type: skirt`` object: ``rings [[y, r], …]`` (``y`` strictly increasing,
``r > 0``), ``sway {amplitude, turns, lag_deg, phase_deg}``, ``flare {amplitude,
cycles}``, ``squash {amplitude < 1, turns}`` (all optional, amplitude 0 = off).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from eventrecon.common.errors import InputError
from eventrecon.sim.config import get
from eventrecon.sim.primitives import dot

__all__ = ["Skirt", "parse_skirt", "intersect_skirt"]

_EPS = 1e-9


@dataclass
class Skirt:
    """Rest rings and deformation parameters of a skirt (module docstring).

    Attributes:
        heights, radii: ``[n]`` rest rings ``y_j`` (increasing) and ``r_j``.
        sway: ``(A_s, k_s, ℓ [rad], φ_s [rad])``; flare: ``(A_f, k_f)``; squash: ``(A_q, k_q)``.
    """

    heights: np.ndarray
    radii: np.ndarray
    sway: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    flare: tuple[float, float] = (0.0, 0.0)
    squash: tuple[float, float] = (0.0, 0.0)

    @property
    def v(self) -> np.ndarray:
        """``[n]`` ring parameter ``v_j`` (0 at the top ring, 1 at the hem)."""
        return (self.heights - self.heights[0]) / (self.heights[-1] - self.heights[0])

    @property
    def deforms(self) -> bool:
        return any(a != 0 and k != 0 for a, k in ((self.sway[0], self.sway[1]),
                                                 (self.flare[0], self.flare[1]),
                                                 (self.squash[0], self.squash[1])))

    def ring_terms(self, t: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Ring ellipses at times ``t [N]``, component-wise: ``(c_x, c_z, s)`` ``[N, n]``
        and the entries ``(M_00, M_01, M_11)`` ``[N, 1]`` of the symmetric
        ``M = E^{-1} = Q(β) diag(1/(1+A_q), 1/(1−A_q)) Q(β)ᵀ``."""
        v = torch.as_tensor(self.v, dtype=t.dtype, device=t.device)[None]
        r = torch.as_tensor(self.radii, dtype=t.dtype, device=t.device)[None]
        amp, turns, lag, phase = self.sway
        psi = phase + 2 * math.pi * turns * t[:, None] - lag * v
        c = amp * v ** 2
        fa, fk = self.flare
        s = r * (1 + fa * v * 0.5 * (1 - torch.cos(2 * math.pi * fk * t))[:, None])
        qa, qk = self.squash
        beta = 2 * math.pi * qk * t[:, None]
        cb, sb = torch.cos(beta), torch.sin(beta)
        p, q = 1 / (1 + qa), 1 / (1 - qa)
        return (c * torch.sin(psi), c * torch.cos(psi), s, cb * cb * p + sb * sb * q,
                cb * sb * (p - q), sb * sb * p + cb * cb * q)

    def rings(self, t: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Ring ellipses at times ``t [N]``.

        Returns:
            ``(c [N, n, 2], s [N, n], M [N, 2, 2])``: centres ``(x, z)``, scales and the
            shared inverse shape matrix ``M = E^{-1}``.
        """
        cx, cz, s, m00, m01, m11 = self.ring_terms(t)
        M = torch.stack([torch.cat([m00, m01], -1), torch.cat([m01, m11], -1)], -2)
        return torch.stack([cx, cz], -1), s, M

    def bound_radius(self) -> float:
        """Radius about the local origin containing the skirt at every time: the sheet
        is a convex combination of its rings, so ``max_j √(y_j² + ρ_j²)`` with
        ``ρ_j = A_s v_j² + r_j (1 + |A_f| v_j)(1 + A_q)`` bounds it."""
        rho = (abs(self.sway[0]) * self.v ** 2
               + self.radii * (1 + abs(self.flare[0]) * self.v) * (1 + self.squash[0]))
        return float(np.sqrt(self.heights ** 2 + rho ** 2).max())

    def radial_range(self) -> tuple[np.ndarray, np.ndarray]:
        """``(ρ_min [n], ρ_max [n])``: bounds of the distance of ring ``j`` from the axis
        at every time (sway, flare and squash at their extremes)."""
        v, r = self.v, self.radii
        sway = abs(self.sway[0]) * v ** 2
        fa = self.flare[0]
        hi = r * (1 + max(fa, 0.0) * v) * (1 + self.squash[0]) + sway
        lo = r * (1 + min(fa, 0.0) * v) * (1 - self.squash[0]) - sway
        return np.maximum(lo, 0.0), hi

    def band_spheres(self, sectors: int = 16) -> tuple[np.ndarray, np.ndarray]:
        """Local spheres ``(centres [B·S, 3], radii [B·S])`` whose union holds the skirt at
        every time: band ``j`` lies in the annular shell ``y ∈ [y_j, y_{j+1}]``,
        ``ρ ∈ [ρ_lo, ρ_hi]`` (its rings' :meth:`radial_range`; the band is a convex
        combination of them), cut into ``S`` sectors of angle ``Δθ``. A sector's sphere
        sits at ``ρ_c = (ρ_lo + ρ_hi)/2`` on its middle angle, at mid height, with radius
        ``√(max_{ρ∈{ρ_lo, ρ_hi}}(ρ² + ρ_c² − 2ρρ_c cos(Δθ/2)) + (Δy/2)²)``, the
        distance to the sector's farthest corner."""
        lo, hi = self.radial_range()
        lo, hi = np.minimum(lo[1:], lo[:-1]), np.maximum(hi[1:], hi[:-1])        # [B]
        rc = (lo + hi) / 2
        half_t = math.pi / sectors
        rxz2 = np.maximum(lo ** 2 + rc ** 2 - 2 * lo * rc * math.cos(half_t),
                          hi ** 2 + rc ** 2 - 2 * hi * rc * math.cos(half_t))
        mid, half_y = (self.heights[1:] + self.heights[:-1]) / 2, np.diff(self.heights) / 2
        th = (np.arange(sectors) + 0.5) * (2 * half_t)                          # [S]
        y = np.broadcast_to(mid[:, None], (len(mid), sectors))
        centres = np.stack([rc[:, None] * np.sin(th), y, rc[:, None] * np.cos(th)],
                           -1).reshape(-1, 3)
        radii = np.sqrt(rxz2 + half_y ** 2)
        return centres, np.repeat(radii, sectors)

    def ring_points(self, t: Tensor, n_alpha: int = 720) -> tuple[Tensor, float]:
        """Points on every ring at times ``t [T]``: ``([T, n·n_alpha, 3], margin)``.

        The sheet's extremes of any convex function (distance from an axis) and of any
        linear one (height) lie on its rings; ``margin`` bounds how far the true ellipse
        can stick out between the ``n_alpha`` samples.
        """
        c, s, M = self.rings(t)
        a = torch.arange(n_alpha, dtype=t.dtype, device=t.device) * (2 * math.pi / n_alpha)
        u = torch.stack([torch.sin(a), torch.cos(a)], -1)                      # [A, 2]
        E = torch.linalg.inv(M)                                                 # [T, 2, 2]
        q = c[:, :, None] + s[:, :, None, None] * torch.einsum("tij,aj->tai", E, u)[:, None]
        y = torch.as_tensor(self.heights, dtype=t.dtype, device=t.device)
        y = y[None, :, None].expand(q.shape[:3])
        pts = torch.stack([q[..., 0], y, q[..., 1]], -1).reshape(t.shape[0], -1, 3)
        rho = float((s * (1 + self.squash[0])).max())  # safety factor 4 on the sagitta
        return pts, 4 * rho * (1 - math.cos(math.pi / n_alpha)) + 1e-12


def intersect_skirt(o: Tensor, d: Tensor, t: Tensor, sk: Skirt) -> tuple[Tensor, Tensor, Tensor]:
    """Exact ray–skirt intersection in the skirt's local frame (module docstring).

    Args:
        o, d: ``[N, 3]`` origins and unit directions; t: ``[N]`` normalised times.

    Returns:
        ``(τ [N], n [N, 3], p [N, 3])``: distance (``inf`` where missed), unit normal
        facing the ray (``n·d ≤ 0``) and the material point for the texture.

    >>> sk = Skirt(np.array([-0.5, 0.5]), np.array([1.0, 1.0]))   # a unit cylinder sheet
    >>> tau, n, p = intersect_skirt(torch.tensor([[0., 0., -3.]], dtype=torch.float64),
    ...                             torch.tensor([[0., 0., 1.]], dtype=torch.float64),
    ...                             torch.zeros(1, dtype=torch.float64), sk)
    >>> tau.tolist(), (n + 0.0).tolist()
    ([2.0], [[0.0, 0.0, -1.0]])
    """
    cx, cz, s, m00, m01, m11 = sk.ring_terms(t)                  # [N, n] ×3, [N, 1] ×3
    y = torch.as_tensor(sk.heights, dtype=o.dtype, device=o.device)
    dy = (y[1:] - y[:-1])[None]                                  # [1, B]
    dcx, dcz, ds = cx[:, 1:] - cx[:, :-1], cz[:, 1:] - cz[:, :-1], s[:, 1:] - s[:, :-1]
    lam0 = (o[:, 1:2] - y[None, :-1]) / dy                       # [N, B]
    lam1 = d[:, 1:2] / dy
    ux, uz = o[:, 0:1] - cx[:, :-1] - lam0 * dcx, o[:, 2:3] - cz[:, :-1] - lam0 * dcz
    wx, wz = d[:, 0:1] - lam1 * dcx, d[:, 2:3] - lam1 * dcz
    sig0, sig1 = s[:, :-1] + lam0 * ds, lam1 * ds
    mux, muz = m00 * ux + m01 * uz, m01 * ux + m11 * uz          # M u, M w  [N, B]
    mwx, mwz = m00 * wx + m01 * wz, m01 * wx + m11 * wz
    ww = mwx * mwx + mwz * mwz
    a = ww - sig1 * sig1
    b = mux * mwx + muz * mwz - sig0 * sig1
    cc = mux * mux + muz * muz - sig0 * sig0
    disc = b * b - a * cc
    sq = torch.sqrt(disc.clamp_min(0))
    qq = -(b + torch.where(b >= 0, sq, -sq))                     # no cancellation
    inf = torch.full_like(a, float("inf"))
    small = a.abs() <= 1e-14 * ww.clamp_min(1e-300)
    r1 = torch.where(small, torch.where(b != 0, -cc / (2 * b), inf), qq / a)
    r2 = torch.where(small | (qq == 0), inf, cc / torch.where(qq == 0, 1.0, qq))
    best = inf
    for r in (r1, r2):
        lam = lam0 + lam1 * r
        ok = (disc >= 0) & (r > _EPS) & (lam >= 0) & (lam <= 1) & torch.isfinite(r)
        best = torch.minimum(best, torch.where(ok, r, inf))
    tau, band = best.min(-1)                                     # [N]
    hit = torch.isfinite(tau)
    tau_f = torch.where(hit, tau, torch.zeros_like(tau))
    bi = band[:, None]

    def at(x: Tensor) -> Tensor:                                 # the hit band's value
        return x.gather(1, bi)[:, 0]

    lam = (at(lam0) + at(lam1) * tau_f).clamp(0, 1)
    x = o + tau_f[:, None] * d
    m00, m01, m11 = m00[:, 0], m01[:, 0], m11[:, 0]
    px, pz = x[:, 0] - at(cx[:, :-1]) - lam * at(dcx), x[:, 2] - at(cz[:, :-1]) - lam * at(dcz)
    mx, mz = m00 * px + m01 * pz, m01 * px + m11 * pz            # m = M(q − c) = s·u(α)
    sb = at(s[:, :-1]) + lam * at(ds)
    bx, bz = at(dcx), at(dcz)
    gy = -2 * (mx * (m00 * bx + m01 * bz) + mz * (m01 * bx + m11 * bz) + sb * at(ds)) \
        / dy[0, band]
    n = torch.stack([2 * (m00 * mx + m01 * mz), gy, 2 * (m01 * mx + m11 * mz)], -1)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    n = torch.where((dot(n, d) > 0)[:, None], -n, n)
    r = torch.as_tensor(sk.radii, dtype=o.dtype, device=o.device)
    k = r[band] + lam * (r[band + 1] - r[band])                  # rest radius / scale
    k = k / sb.clamp_min(1e-300)
    p = torch.stack([k * mx, x[:, 1], k * mz], -1)
    return tau, torch.where(hit[:, None], n, torch.zeros_like(n)), p


def parse_skirt(raw: Mapping, where: str, pre: str) -> Skirt:
    """Parse the skirt fields of an object (module docstring)."""
    rings = get(raw, "rings", list, where, pre, expect="a list of [y, r] rings")
    try:
        arr = np.asarray(rings, dtype=np.float64)
    except (TypeError, ValueError):
        arr = np.zeros((0, 0))
    if arr.ndim != 2 or arr.shape[0] < 2 or arr.shape[1] != 2 or np.any(np.diff(arr[:, 0]) <= 0) \
            or np.any(arr[:, 1] <= 0):
        raise InputError(where, f"{pre}rings", "at least two [y, r] rows with y strictly "
                         "increasing (downwards) and r > 0", repr(rings)[:60])

    def sub(key: str) -> Mapping:
        return get(raw, key, Mapping, where, pre, default={}, expect="a mapping")

    sw, fl, sq = sub("sway"), sub("flare"), sub("squash")
    num = (float,)
    sway = (get(sw, "amplitude", num, where, f"{pre}sway.", 0.0),
            get(sw, "turns", num, where, f"{pre}sway.", 1.0),
            math.radians(get(sw, "lag_deg", num, where, f"{pre}sway.", 0.0)),
            math.radians(get(sw, "phase_deg", num, where, f"{pre}sway.", 0.0)))
    flare = (get(fl, "amplitude", num, where, f"{pre}flare.", 0.0, lambda v: v > -1,
                 "an amplitude > −1"),
             get(fl, "cycles", num, where, f"{pre}flare.", 1.0))
    squash = (get(sq, "amplitude", num, where, f"{pre}squash.", 0.0, lambda v: 0 <= v < 1,
                  "an amplitude in [0, 1)"),
              get(sq, "turns", num, where, f"{pre}squash.", 1.0))
    return Skirt(arr[:, 0].copy(), arr[:, 1].copy(), sway, flare, squash)
