"""Exact ray casting of the procedural primitives and Lambertian shading, batched.

Every ray carries its own time, so one call renders pixels at different instants
(what the adaptive event sampler needs). All geometry runs in float64.

Intersections are computed in the object's local frame: with pose ``x_w = R x_l + c``,
``o_l = Rᵀ(o − c)``, ``d_l = Rᵀ d`` (still unit, so the ray parameter is the same
metric distance), and the local normal is mapped back as ``n_w = R n_l``.

- sphere ``|x| = r``: ``s = −b − √(b² − |o|² + r²)``, ``b = o·d`` (the far root when the
  near one is behind the origin);
- box ``|x_i| ≤ h_i`` (slabs): ``s = max_i min(s⁻_i, s⁺_i)`` if it does not exceed
  ``min_i max(s⁻_i, s⁺_i)``, normal along the entering slab's axis;
- plane ``y = h``: ``s = (h − o_y)/d_y`` (kept if ``x² + z² ≤ radius²``), normal
  ``(0, −1, 0)`` (up).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from eventrecon.render.cameras import Cameras
from eventrecon.sim.scene import Scene, SceneObject

__all__ = ["intersect_sphere", "intersect_box", "intersect_plane", "Renderer", "PixelRenderer"]

_EPS = 1e-9
_CHUNK = 1 << 18


def intersect_sphere(o: Tensor, d: Tensor, radius: float) -> Tensor:
    """Distance to a centred sphere along unit rays; ``inf`` where missed.

    Args:
        o, d: ``[N, 3]`` origins and unit directions (local frame).

    >>> intersect_sphere(torch.tensor([[0., 0., -3.]]), torch.tensor([[0., 0., 1.]]), 1.0)
    tensor([2.])
    """
    b = (o * d).sum(-1)
    c = (o * o).sum(-1) - radius * radius
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


def _to_local(R: Tensor, v: Tensor) -> Tensor:
    """``Rᵀ v`` for ``R [3, 3]`` or ``[N, 3, 3]`` and ``v [N, 3]``."""
    return v @ R if R.dim() == 2 else torch.einsum("nji,nj->ni", R, v)


class Renderer:
    """Linear radiance of rays at per-ray times: ``radiance(o, d, t) -> [N, 3]``."""

    def __init__(self, scene: Scene):
        self.scene = scene
        self._light = None

    def _hit(self, obj: SceneObject, o: Tensor, d: Tensor, t: Tensor
             ) -> tuple[Tensor, Tensor, Tensor]:
        """``(s [N], n_world [N, 3], p_local [N, 3])`` for one object."""
        if obj.kind == "plane":
            s = intersect_plane(o, d, obj.height)
            p = o + torch.nan_to_num(s, posinf=0.0)[:, None] * d
            s = torch.where(p[:, 0] ** 2 + p[:, 2] ** 2 <= obj.radius ** 2, s,
                            torch.full_like(s, float("inf")))
            n = torch.zeros_like(o)
            n[:, 1] = -1.0
            p[:, 1] -= obj.height
            return s, n, p
        R, c = obj.pose(t if obj.moves else t[:1])
        ol, dl = _to_local(R, o - c), _to_local(R, d)
        if obj.kind == "sphere":
            s = intersect_sphere(ol, dl, obj.radius)
            pl = ol + torch.nan_to_num(s, posinf=0.0)[:, None] * dl
            nl = pl / obj.radius
        else:
            s, nl = intersect_box(ol, dl, torch.as_tensor(obj.half_size, dtype=o.dtype,
                                                          device=o.device))
            pl = ol + torch.nan_to_num(s, posinf=0.0)[:, None] * dl
        nw = nl @ R.T if R.dim() == 2 else torch.einsum("nij,nj->ni", R, nl)
        return s, nw, pl

    def radiance(self, o: Tensor, d: Tensor, t: Tensor) -> Tensor:
        """Shade rays ``o, d [N, 3]`` (unit ``d``) at normalised times ``t [N]``.

        Returns:
            ``[N, 3]`` float64 linear radiance (formula in :mod:`eventrecon.sim.scene`).
        """
        if o.shape[0] > _CHUNK:
            return torch.cat([self.radiance(o[i:i + _CHUNK], d[i:i + _CHUNK], t[i:i + _CHUNK])
                              for i in range(0, o.shape[0], _CHUNK)])
        sc = self.scene
        o, d, t = o.double(), d.double(), t.double()
        n_rays = o.shape[0]
        best = torch.full((n_rays,), float("inf"), dtype=o.dtype, device=o.device)
        normal = torch.zeros_like(o)
        albedo = torch.zeros_like(o)
        for obj in sc.objects:
            sel = torch.arange(n_rays, device=o.device)
            if obj.kind != "plane":  # cull by the bounding sphere of the whole motion
                centre, rad = obj.hull()
                sel = sel[intersect_sphere(o - torch.as_tensor(centre, dtype=o.dtype,
                                                               device=o.device), d,
                                           rad + 1e-6).isfinite()]
                if sel.numel() == 0:
                    continue
            s, n, p = self._hit(obj, o[sel], d[sel], t[sel])
            win = s < best[sel]
            idx = sel[win]
            best[idx] = s[win]
            normal[idx] = n[win]
            albedo[idx] = obj.texture.albedo(p[win])
        lt = torch.as_tensor(sc.light.direction, dtype=o.dtype, device=o.device)
        shade = sc.light.ambient + sc.light.intensity * (normal @ lt).clamp_min(0)
        rgb = albedo * shade[:, None] * torch.as_tensor(sc.light.color, dtype=o.dtype,
                                                        device=o.device)
        bg = torch.as_tensor(sc.background, dtype=o.dtype, device=o.device)
        return torch.where(best.isfinite()[:, None], rgb, bg.expand(n_rays, 3))


class PixelRenderer:
    """The pixels of a camera set, rendered at any times (``s×s`` supersampled).

    Pixels are indexed globally, ``g = view·H·W + row·W + col``.
    """

    def __init__(self, scene: Scene, cams: Cameras, supersample: int = 1):
        self.renderer = Renderer(scene)
        self.cams, self.ss = cams, int(supersample)
        H, W, V = cams.height, cams.width, len(cams)
        off = (torch.arange(self.ss, dtype=torch.float64) + 0.5) / self.ss - 0.5
        oy, ox = torch.meshgrid(off, off, indexing="ij")
        sub = torch.stack([ox.reshape(-1), oy.reshape(-1)], -1)            # [S, 2]
        uv = (cams.pixel_grid()[:, None, :] + sub[None]).reshape(-1, 2)   # [H*W*S, 2]
        os_, ds = [], []
        for v in range(V):
            view = torch.full((uv.shape[0],), v, dtype=torch.long)
            dc = cams.pixel_directions(view, uv)
            dw = torch.einsum("ij,nj->ni", cams.c2w[v, :3, :3], dc)
            ds.append(dw / dw.norm(dim=-1, keepdim=True))
            os_.append(cams.c2w[v, :3, 3].expand_as(dw))
        S = self.ss * self.ss
        self.o = torch.cat(os_).reshape(V * H * W, S, 3)
        self.d = torch.cat(ds).reshape(V * H * W, S, 3)
        self.n_pixels = V * H * W

    def radiance(self, pix: Tensor, t: Tensor) -> Tensor:
        """``[N, 3]`` linear radiance of global pixels ``pix [N]`` at times ``t [N]``."""
        S = self.ss * self.ss
        o = self.o[pix].reshape(-1, 3)
        d = self.d[pix].reshape(-1, 3)
        rgb = self.renderer.radiance(o, d, t.double().repeat_interleave(S))
        return rgb.reshape(-1, S, 3).mean(1)

    def image(self, view: int, t: float) -> Tensor:
        """``[H, W, 3]`` linear radiance of one view at time ``t``."""
        return self.images(view, torch.tensor([float(t)], dtype=torch.float64))[0]

    def images(self, view: int, times: Tensor) -> Tensor:
        """``[T, H, W, 3]`` linear radiance of one view at times ``[T]`` (one batched call)."""
        H, W = self.cams.height, self.cams.width
        times = torch.as_tensor(times, dtype=torch.float64).reshape(-1)
        pix = torch.arange(view * H * W, (view + 1) * H * W).repeat(times.numel())
        return self.radiance(pix, times.repeat_interleave(H * W)).reshape(-1, H, W, 3)

    def activity(self, n_intervals: int, chunk: int = 8192) -> tuple[np.ndarray, np.ndarray]:
        """Which pixels may change in which of ``n_intervals`` equal time intervals.

        A pixel is *busy* in interval ``k`` if one of its rays meets the interval sphere
        (:meth:`SceneObject.interval_spheres`) of a moving object; otherwise its radiance
        is constant over the whole closed interval (no shadows, static cameras). All
        rays of a view share its centre ``o``, so the test is a cone test,
        ``d·û ≥ √(1 − R²/D²)`` with ``û, D`` the direction and distance of the sphere
        centre from ``o`` -- one matrix product per view.

        Returns:
            ``(pix [M] int64, busy [M, K] bool)`` for the pixels busy at least once.
        """
        H, W = self.cams.height, self.cams.width
        S = self.ss * self.ss
        spheres = [o.interval_spheres(n_intervals) for o in self.renderer.scene.moving]
        pix_out, busy_out = [], []
        for v in range(len(self.cams)):
            origin = self.cams.c2w[v, :3, 3].numpy()
            cols, lims = [], []
            for centres, radii in spheres:
                u = centres - origin
                D = np.linalg.norm(u, axis=1)
                cols.append(u / D[:, None])
                lims.append(np.where(D > radii, np.sqrt(np.clip(1 - (radii / D) ** 2, 0, 1)),
                                     -2.0))
            if not cols:
                break
            U, lim = np.concatenate(cols).T, np.concatenate(lims)        # [3, n_obj·K]
            dirs = self.d[v * H * W:(v + 1) * H * W].numpy()              # [HW, S, 3]
            for a in range(0, H * W, chunk):
                dd = dirs[a:a + chunk].reshape(-1, 3)
                hit = (dd @ U >= lim).reshape(-1, S, len(spheres), n_intervals)
                b = hit.any(axis=(1, 2))
                keep = b.any(1)
                pix_out.append(v * H * W + a + np.nonzero(keep)[0])
                busy_out.append(b[keep])
        if not pix_out:
            return np.zeros(0, np.int64), np.zeros((0, n_intervals), bool)
        return np.concatenate(pix_out).astype(np.int64), np.concatenate(busy_out)
