"""The clipping volume: a vertical cylinder intersected with the unit sphere.

The subject of every scene lies inside the cylinder

.. math:: \\mathcal{C}_r = \\{(x, y, z) : x^2 + z^2 \\le r^2,\\ y_{min} \\le y \\le y_{max}\\}

whose axis is the world y axis (up is −y, so ``y_max`` is the floor side). Density is
zero outside :math:`\\mathcal{C}_r` and the sampling range of a ray
:math:`\\mathbf{o} + s\\,\\mathbf{d},\\ s \\ge 0` is cut to
:math:`\\mathcal{C}_r \\cap \\{\\lVert \\mathbf{p} \\rVert \\le 1\\}`. Defaults
``r = 0.5, y ∈ [−0.75, 0.25]``; the "w/o clipping" ablation is ``r = 1, y ∈ [−1, 1]``
(still intersected with the unit sphere). ``radius_scale`` multiplies ``r``: schedules
anneal it (the NGP baseline grows it from 0 to 1).

All three pieces are convex, so the intersection with a ray is one interval, the
intersection of three exact intervals:

- sphere: :math:`(\\mathbf{d}\\cdot\\mathbf{d}) s^2 + 2 (\\mathbf{o}\\cdot\\mathbf{d}) s
  + \\mathbf{o}\\cdot\\mathbf{o} - 1 \\le 0`;
- infinite cylinder: :math:`a s^2 + 2 b s + c \\le 0` with :math:`a = d_x^2 + d_z^2`,
  :math:`b = o_x d_x + o_z d_z`, :math:`c = o_x^2 + o_z^2 - r^2`; a ray parallel to the
  axis (:math:`a < 10^{-12}`, i.e. a horizontal drift below 2·10⁻⁶ over the sphere's
  diameter) is inside for all ``s`` if :math:`c \\le 0`, else never;
- slab: :math:`y_{min} \\le o_y + s d_y \\le y_{max}`; a horizontal ray
  (:math:`|d_y| < 10^{-12}`) is inside for all ``s`` if :math:`o_y` is in the slab.

The roots are computed in float64 (per ray, so cheap) and returned in the input dtype.
A ray with a NaN coordinate misses.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from eventrecon.common.errors import InputError

__all__ = ["Cylinder", "INSIDE_TOL", "PARALLEL_EPS", "NO_CLIPPING"]

#: The "w/o clipping" ablation's cylinder: it covers the unit sphere's box.
NO_CLIPPING: dict[str, float] = {"radius": 1.0, "y_min": -1.0, "y_max": 1.0}
#: Squared-norm threshold below which a direction counts as parallel to an axis/plane.
PARALLEL_EPS = 1e-12
#: The renderer's slack (world units) when testing sample points against the cylinder:
#: points computed at an interval's ends may land one ulp outside.
INSIDE_TOL = 1e-5


def _quadratic_interval(a: Tensor, b: Tensor, c: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Interval where ``a s² + 2 b s + c ≤ 0`` for ``a > 0`` (float64, elementwise).

    Returns ``(lo, hi, ok)``; ``ok`` is False where the discriminant ``b² − a c`` is
    negative (no real roots; ``lo``/``hi`` are then finite but meaningless). Uses the
    cancellation-free form ``q = −(b + sign(b)√disc)``, roots ``q / a`` and ``c / q``.
    """
    disc = b * b - a * c
    ok = disc >= 0
    sq = disc.clamp(min=0).sqrt()
    sign = torch.where(b >= 0, torch.ones_like(b), -torch.ones_like(b))
    q = -(b + sign * sq)
    r1 = q / a
    q_safe = torch.where(q == 0, torch.ones_like(q), q)
    r2 = torch.where(q == 0, r1, c / q_safe)
    return torch.minimum(r1, r2), torch.maximum(r1, r2), ok


@dataclass(frozen=True)
class Cylinder:
    """Vertical clipping cylinder ``x² + z² ≤ r², y ∈ [y_min, y_max]`` (∩ unit sphere).

    Args:
        radius: cylinder radius ``r`` (world units, > 0).
        y_min, y_max: extent along the axis (up is −y, so ``y_max`` is the floor side).

    >>> cyl = Cylinder(radius=0.5, y_min=-0.75, y_max=0.25)
    >>> near, far, hit = cyl.ray_interval(torch.tensor([[-2.0, -0.25, 0.0]]),
    ...                                   torch.tensor([[1.0, 0.0, 0.0]]))
    >>> near.item(), far.item(), hit.item()
    (1.5, 2.5, True)
    """

    radius: float = 0.5
    y_min: float = -0.75
    y_max: float = 0.25

    def __post_init__(self) -> None:
        if not self.radius > 0:
            raise InputError("clipping", "radius", "a positive number", self.radius)
        if not self.y_min < self.y_max:
            raise InputError("clipping", "y_min/y_max", "y_min < y_max",
                             f"{self.y_min}, {self.y_max}")

    def ray_interval(
        self, o: Tensor, d: Tensor, radius_scale: float = 1.0
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Parameter interval of each ray inside the cylinder ∩ unit sphere.

        Args:
            o: ``[N, 3]`` ray origins.
            d: ``[N, 3]`` ray directions (unit length for metric ``s``; any non-zero
                length works, ``s`` is then in units of ``|d|``).
            radius_scale: factor in ``[0, ∞)`` applied to the radius; 0 contains nothing.

        Returns:
            ``(near [N], far [N], hit [N] bool)`` in ``o``'s dtype: ``0 ≤ near < far``
            where ``hit``; for rays that miss (or touch along a zero-length interval),
            ``hit`` is False and ``near = far = 0``.
        """
        if radius_scale < 0:
            raise InputError("clipping", "radius_scale", "a number >= 0", radius_scale)
        dtype = o.dtype
        o64, d64 = o.double(), d.double()
        ox, oy, oz = o64.unbind(-1)
        dx, dy, dz = d64.unbind(-1)
        inf = torch.full_like(ox, float("inf"))

        # Unit sphere (d·d > 0 always for a valid ray).
        lo, hi, hit = _quadratic_interval((d64 * d64).sum(-1), (o64 * d64).sum(-1),
                                          (o64 * o64).sum(-1) - 1.0)
        lo = lo.clamp(min=0.0)

        # Infinite cylinder around the y axis.
        r = self.radius * radius_scale
        a = dx * dx + dz * dz
        c = ox * ox + oz * oz - r * r
        parallel = a < PARALLEL_EPS
        c_lo, c_hi, c_ok = _quadratic_interval(torch.where(parallel, torch.ones_like(a), a),
                                               ox * dx + oz * dz, c)
        lo = torch.maximum(lo, torch.where(parallel, -inf, c_lo))
        hi = torch.minimum(hi, torch.where(parallel, inf, c_hi))
        hit = hit & torch.where(parallel, c <= 0, c_ok) & (r > 0)

        # Slab y_min <= y <= y_max.
        flat = dy.abs() < PARALLEL_EPS
        dy_safe = torch.where(flat, torch.ones_like(dy), dy)
        s1, s2 = (self.y_min - oy) / dy_safe, (self.y_max - oy) / dy_safe
        lo = torch.maximum(lo, torch.where(flat, -inf, torch.minimum(s1, s2)))
        hi = torch.minimum(hi, torch.where(flat, inf, torch.maximum(s1, s2)))
        hit = hit & torch.where(flat, (oy >= self.y_min) & (oy <= self.y_max), True)

        hit = hit & (hi > lo)
        zero = torch.zeros_like(lo)
        near = torch.where(hit, lo, zero)
        far = torch.where(hit, hi, zero)
        return near.to(dtype), far.to(dtype), hit

    def box(self) -> tuple[list[float], list[float]]:
        """The cylinder's bounding box ``([−r, y_min, −r], [r, y_max, r])``.

        >>> Cylinder(0.5, -0.75, 0.25).box()
        ([-0.5, -0.75, -0.5], [0.5, 0.25, 0.5])
        """
        r = self.radius
        return [-r, self.y_min, -r], [r, self.y_max, r]

    def inside(self, xyz: Tensor, radius_scale: float = 1.0, tol: float = 0.0) -> Tensor:
        """Membership of points in the (scaled) cylinder.

        Args:
            xyz: ``[..., 3]`` points.
            radius_scale: factor applied to the radius (0: nothing is inside).
            tol: absolute slack on the radius and the y limits (for points computed at
                the interval ends, which rounding may put one ulp outside).

        Returns:
            ``[...]`` bool, ``x² + z² ≤ (r·scale + tol)²`` and
            ``y_min − tol ≤ y ≤ y_max + tol``.
        """
        r = self.radius * radius_scale
        if r <= 0:
            return torch.zeros(xyz.shape[:-1], dtype=torch.bool, device=xyz.device)
        x, y, z = xyz.unbind(-1)
        return ((x * x + z * z <= (r + tol) ** 2)
                & (y >= self.y_min - tol) & (y <= self.y_max + tol))
