"""OpenCV lens distortion on normalised image coordinates, and its inverse.

``dist = (k1, k2, p1, p2, k3)`` maps undistorted ``(x, y) = (X/Z, Y/Z)`` to

.. math::
   r^2 = x^2 + y^2,\\quad
   x_d = x(1 + k_1 r^2 + k_2 r^4 + k_3 r^6) + 2 p_1 x y + p_2 (r^2 + 2x^2),\\\\
   y_d = y(1 + k_1 r^2 + k_2 r^4 + k_3 r^6) + p_1 (r^2 + 2y^2) + 2 p_2 x y.

Undistortion inverts that map by vectorised Newton iterations with the analytic 2×2
Jacobian (all pixels at once, no per-pixel solver loop).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["distort", "undistort"]


def distort(xy: Tensor, dist: Tensor) -> Tensor:
    """Apply OpenCV distortion to normalised coordinates.

    Args:
        xy: ``[..., 2]`` undistorted normalised coordinates ``(X/Z, Y/Z)``.
        dist: ``[..., 5]`` (broadcastable) coefficients ``(k1, k2, p1, p2, k3)``.

    Returns:
        ``[..., 2]`` distorted normalised coordinates (formula in the module docstring).

    >>> distort(torch.tensor([[0.5, 0.0]]), torch.tensor([0.1, 0.0, 0.0, 0.0, 0.0]))
    tensor([[0.5125, 0.0000]])
    """
    x, y = xy[..., 0], xy[..., 1]
    k1, k2, p1, p2, k3 = (dist[..., i] for i in range(5))
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return torch.stack([xd, yd], dim=-1)


def _distort_jacobian(xy: Tensor, dist: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Entries ``(a, b, c, d)`` of ``J = [[a, b], [c, d]] = ∂(xd, yd)/∂(x, y)``."""
    x, y = xy[..., 0], xy[..., 1]
    k1, k2, p1, p2, k3 = (dist[..., i] for i in range(5))
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial_dr2 = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    a = radial + 2 * x * x * dradial_dr2 + 2 * p1 * y + 6 * p2 * x
    b = 2 * x * y * dradial_dr2 + 2 * p1 * x + 2 * p2 * y
    c = 2 * x * y * dradial_dr2 + 2 * p1 * x + 2 * p2 * y
    d = radial + 2 * y * y * dradial_dr2 + 6 * p1 * y + 2 * p2 * x
    return a, b, c, d


def undistort(xy_d: Tensor, dist: Tensor, iters: int = 20, tol: float = 1e-12) -> Tensor:
    """Invert :func:`distort` by Newton's method, vectorised over all points.

    Solves ``distort(x) = xy_d`` starting from ``x = xy_d``; each step is
    ``x ← x − J(x)^{-1} (distort(x) − xy_d)`` with the closed-form 2×2 inverse.
    Computed in float64 whatever the input dtype, returned in the input dtype.

    Args:
        xy_d: ``[..., 2]`` distorted normalised coordinates.
        dist: ``[..., 5]`` coefficients (broadcastable to ``xy_d[..., :1]``).

    Returns:
        ``[..., 2]`` undistorted normalised coordinates with
        ``|distort(x) − xy_d| < tol`` wherever the map is invertible.

    >>> d = torch.tensor([-0.4, 0.2, 0.001, -0.002, 0.0])
    >>> x = torch.tensor([[0.3, -0.2]])
    >>> torch.allclose(undistort(distort(x, d), d), x, atol=1e-9)
    True
    """
    dtype = xy_d.dtype
    target = xy_d.double()
    dist = dist.double()
    if not bool(dist.abs().gt(0).any()):
        return xy_d.clone()
    x = target.clone()
    for _ in range(iters):
        res = distort(x, dist) - target
        if float(res.abs().max()) < tol:
            break
        a, b, c, d = _distort_jacobian(x, dist)
        det = a * d - b * c
        det = torch.where(det.abs() < 1e-12, torch.full_like(det, 1e-12), det)
        dx = (d * res[..., 0] - b * res[..., 1]) / det
        dy = (-c * res[..., 0] + a * res[..., 1]) / det
        x = x - torch.stack([dx, dy], dim=-1)
    return x.to(dtype)
