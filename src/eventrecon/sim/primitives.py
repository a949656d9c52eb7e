"""Exact ray–primitive intersections (float64): sphere, box, plane, and box batches.

All in the primitive's local frame, unit directions ``d`` (the ray parameter is the
metric distance):

- sphere ``|x| = r``: ``s = −b − √(b² − |o|² + r²)``, ``b = o·d`` (the far root when the
  near one is behind the origin);
- box ``|x_i| ≤ h_i`` (slabs): ``s = max_i min(s⁻_i, s⁺_i)`` if it does not exceed
  ``min_i max(s⁻_i, s⁺_i)``, normal along the entering slab's axis;
- plane ``y = h``: ``s = (h − o_y)/d_y``.

:class:`BoxSet` runs the slab test of ``K`` boxes at once (one call instead of ``K``),
each box fixed in one of a few frames (the rigid bodies of an articulated model);
:class:`SphereSet` does the same for spheres.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from eventrecon.sim.texture import Texture, TextureTable

__all__ = ["intersect_sphere", "intersect_box", "intersect_plane", "BoxSet", "SphereSet", "dot"]

_EPS = 1e-9


def dot(a: Tensor, b: Tensor) -> Tensor:
    """Dot products over the last axis, ``[..., k] × [..., k] -> [...]``, as a matrix
    product with ones (several times faster than ``.sum(-1)`` over 2 or 3 entries).

    >>> dot(torch.tensor([[1., 2., 3.]]), torch.tensor([[4., 5., 6.]]))
    tensor([32.])
    """
    return (a * b) @ torch.ones(a.shape[-1], dtype=a.dtype, device=a.device)


def intersect_sphere(o: Tensor, d: Tensor, radius: float) -> Tensor:
    """Distance to a centred sphere along unit rays; ``inf`` where missed.

    Args:
        o, d: ``[N, 3]`` origins and unit directions (local frame).

    >>> intersect_sphere(torch.tensor([[0., 0., -3.]]), torch.tensor([[0., 0., 1.]]), 1.0)
    tensor([2.])
    """
    b = dot(o, d)
    c = dot(o, o) - radius * radius
    disc = b * b - c
    sq = torch.sqrt(disc.clamp_min(0))
    s = torch.where(-b - sq > _EPS, -b - sq, -b + sq)
    return torch.where((disc >= 0) & (s > _EPS), s, torch.full_like(s, float("inf")))


def intersect_box(o: Tensor, d: Tensor, half: Tensor) -> tuple[Tensor, Tensor]:
    """Distance and outward unit normal of an axis-aligned centred box ``|x_i| ≤ half_i``.

    Returns:
        ``(s [N], n [N, 3])``; ``s = inf`` where missed.

    >>> s, n = intersect_box(torch.tensor([[0., 0., -3.]]), torch.tensor([[0., 0., 1.]]),
    ...                      torch.tensor([1., 1., 0.5]))
    >>> s, n
    (tensor([2.5000]), tensor([[ 0.,  0., -1.]]))
    """
    d_safe = torch.where(d.abs() < 1e-300, torch.full_like(d, 1e-300), d)
    inv = 1.0 / d_safe
    s1, s2 = (-half - o) * inv, (half - o) * inv
    near, far = torch.minimum(s1, s2), torch.maximum(s1, s2)
    s_in, axis = near.max(-1)
    s_out = far.min(-1).values
    inside = s_in <= _EPS
    s = torch.where(inside, s_out, s_in)
    hit = (s_in <= s_out) & (s > _EPS)
    if bool(inside.any()):
        axis = torch.where(inside, far.argmin(-1), axis)
    n = torch.zeros_like(o)
    d_axis = d_safe.gather(1, axis[:, None])[:, 0]
    sign = torch.where(inside, 1.0, -1.0).to(o.dtype) * torch.sign(d_axis)
    n.scatter_(1, axis[:, None], sign[:, None])
    return torch.where(hit, s, torch.full_like(s, float("inf"))), n


def intersect_plane(o: Tensor, d: Tensor, height: float) -> Tensor:
    """Distance to the plane ``y = height`` (``inf`` where parallel or behind)."""
    dy = torch.where(d[:, 1].abs() < 1e-300, torch.full_like(d[:, 1], 1e-300), d[:, 1])
    s = (height - o[:, 1]) / dy
    return torch.where(s > _EPS, s, torch.full_like(s, float("inf")))


class _BodySet:
    """``K`` primitives, each fixed in one of ``B`` bodies: what :class:`BoxSet` and
    :class:`SphereSet` share — orientation ``R_k`` and centre ``c_k`` in body ``b_k``, one
    texture each, and the chunking of the ``[n, K]`` ray–primitive pairs."""

    #: Ray–primitive pairs per pass (bounds the ``[n, K, 3]`` temporaries).
    PAIRS = 1 << 19

    def __init__(self, rotations: np.ndarray, centres: np.ndarray, textures: list[Texture],
                 ids: list[int], bodies: list[int]):
        self.R = torch.as_tensor(np.asarray(rotations, np.float64))
        self.c = torch.as_tensor(np.asarray(centres, np.float64))
        self.table = TextureTable(textures)
        self.ids = torch.as_tensor(ids, dtype=torch.long)
        self.body = torch.as_tensor(bodies, dtype=torch.long)

    def __len__(self) -> int:
        return int(self.c.shape[0])

    def intersect(self, o: Tensor, d: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Nearest primitive along rays given in every body's frame, ``o, d [N, B, 3]``.

        Returns:
            ``(s [N], k [N], n [N, 3], albedo [N, 3])``: distance (``inf`` = none), the
            primitive's position in the set (−1 = none), its outward normal in its body's
            frame and its texture's albedo at the hit.
        """
        step = max(1, self.PAIRS // len(self))
        if o.shape[0] > step:
            parts = [self._nearest(o[i:i + step], d[i:i + step])
                     for i in range(0, o.shape[0], step)]
            return tuple(torch.cat([p[j] for p in parts]) for j in range(4))  # type: ignore
        return self._nearest(o, d)

    def _nearest(self, o: Tensor, d: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        raise NotImplementedError


class BoxSet(_BodySet):
    """``K`` boxes, each fixed in one of ``B`` frames (*bodies*), tested together.

    Box ``k`` has pose ``x_body = R_k x_k + c_k`` in body ``b_k``; a ray given in every
    body's frame (``o_b, d_b``) reaches the box frame as ``o_k = R_kᵀ(o_{b_k} − c_k)``,
    ``d_k = R_kᵀ d_{b_k}``. Only ray–box pairs whose ray meets the box's bounding sphere
    run the slab test (:func:`intersect_box`); the nearest hit of each ray wins (ties:
    the box listed first).

    Args:
        rotations: ``[K, 3, 3]`` ``R_k``; centres: ``[K, 3]`` ``c_k``; halves: ``[K, 3]``
            half-extents; textures: one per box; ids: ``[K]`` labels of the boxes (their
            indices in the scene); bodies: ``[K]`` body index ``b_k`` of each box.
    """

    def __init__(self, rotations: np.ndarray, centres: np.ndarray, halves: np.ndarray,
                 textures: list[Texture], ids: list[int], bodies: list[int]):
        super().__init__(rotations, centres, textures, ids, bodies)
        self.half = torch.as_tensor(np.asarray(halves, np.float64))
        self.rad2 = (torch.linalg.norm(self.half, dim=-1) + 1e-6) ** 2     # bounding spheres

    def _nearest(self, o: Tensor, d: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """:meth:`_BodySet.intersect` for one chunk of rays (ties: the box listed first)."""
        N = o.shape[0]
        u = o[:, self.body] - self.c                                       # [N, K, 3]
        dk = d[:, self.body]
        b = dot(u, dk)
        disc = b * b - dot(u, u) + self.rad2
        ray, k = ((disc >= 0) & (torch.sqrt(disc.clamp_min(0)) - b > 0)).nonzero(as_tuple=True)
        R = self.R[k]
        ol = torch.einsum("pj,pji->pi", u[ray, k], R)
        dl = torch.einsum("pj,pji->pi", dk[ray, k], R)
        s_p, n_p = intersect_box(ol, dl, self.half[k])
        s = torch.full((N,), float("inf"), dtype=o.dtype, device=o.device)
        s = s.scatter_reduce(0, ray, s_p, "amin")
        best = (s_p == s[ray]) & torch.isfinite(s_p)
        pair = torch.full((N,), ray.numel(), dtype=torch.long, device=o.device)
        pair = pair.scatter_reduce(0, ray[best], torch.nonzero(best)[:, 0], "amin")
        hit = pair < ray.numel()
        out_k = torch.full((N,), -1, dtype=torch.long, device=o.device)
        n = torch.zeros(N, 3, dtype=o.dtype, device=o.device)
        alb = torch.zeros_like(n)
        if bool(hit.any()):
            w = pair[hit]
            out_k[hit] = k[w]
            n[hit] = torch.einsum("pij,pj->pi", R[w], n_p[w])
            alb[hit] = self.table.albedo(k[w], ol[w] + s_p[w, None] * dl[w])
        return s, out_k, n, alb


class SphereSet(_BodySet):
    """``K`` spheres, each fixed in one of ``B`` bodies (as :class:`BoxSet`), tested
    together: sphere ``k`` of radius ``r_k`` centred at ``c_k`` with orientation ``R_k``
    (for its texture) in body ``b_k``; the hit is :func:`intersect_sphere`'s, the
    nearest over the set wins (ties: the sphere listed first).

    Args:
        rotations: ``[K, 3, 3]``; centres: ``[K, 3]``; radii: ``[K]``; textures, ids,
            bodies: as :class:`BoxSet`.
    """

    def __init__(self, rotations: np.ndarray, centres: np.ndarray, radii: np.ndarray,
                 textures: list[Texture], ids: list[int], bodies: list[int]):
        super().__init__(rotations, centres, textures, ids, bodies)
        self.r = torch.as_tensor(np.asarray(radii, np.float64))

    def _nearest(self, o: Tensor, d: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """:meth:`_BodySet.intersect` for one chunk of rays (ties: the sphere listed first)."""
        N = o.shape[0]
        u = o[:, self.body] - self.c                                       # [N, K, 3]
        dk = d[:, self.body]
        b = dot(u, dk)
        disc = b * b - dot(u, u) + self.r * self.r
        sq = torch.sqrt(disc.clamp_min(0))
        s = torch.where(-b - sq > _EPS, -b - sq, -b + sq)
        s = torch.where((disc >= 0) & (s > _EPS), s, torch.full_like(s, float("inf")))
        s, k = s.min(-1)
        hit = torch.isfinite(s)
        out_k = torch.where(hit, k, torch.full_like(k, -1))
        n = torch.zeros(N, 3, dtype=o.dtype, device=o.device)
        alb = torch.zeros_like(n)
        if bool(hit.any()):
            w = hit.nonzero()[:, 0]
            kw = k[w]
            p = u[w, kw] + s[w, None] * dk[w, kw]                          # body frame
            n[w] = p / self.r[kw, None]
            alb[w] = self.table.albedo(kw, torch.einsum("pj,pji->pi", p, self.R[kw]))
        return s, out_k, n, alb
