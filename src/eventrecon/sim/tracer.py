"""Exact ray casting of a procedural scene and Lambertian shading, batched: :class:`Renderer`.

Every ray carries its own time, so one call renders pixels at different instants
(what the adaptive event sampler needs). All geometry runs in float64.

The scene is a tree (groups are joints, :mod:`eventrecon.sim.scene`). A primitive's
world pose at a ray's time is the composition of its pose and its parents',
``x_w = R_w x_l + c_w``; the ray enters its frame as ``o_l = R_wᵀ(o − c_w)``,
``d_l = R_wᵀ d`` (still unit, so the ray parameter stays the metric distance), and the
local normal goes back as ``n_w = R_w n_l``. The primitives' exact intersections are in
:mod:`eventrecon.sim.primitives` (sphere, box, plane; boxes and spheres are tested in
sets, :class:`~eventrecon.sim.primitives.BoxSet`,
:class:`~eventrecon.sim.primitives.SphereSet`) and :mod:`eventrecon.sim.skirt`.

A ray's *subject* flag (:meth:`Renderer.is_subject`, the masks) says whether its
nearest hit is an object the background images leave out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from eventrecon.sim.primitives import (
    BoxSet,
    SphereSet,
    intersect_box,
    intersect_plane,
    intersect_sphere,
)
from eventrecon.sim.scene import Scene, SceneObject
from eventrecon.sim.skirt import intersect_skirt

__all__ = ["Hits", "Renderer", "PARTS", "CHUNK"]

#: Rays per call of :meth:`Renderer.radiance` (bounds the temporaries).
CHUNK = 1 << 18


def _to_local(R: Tensor, v: Tensor) -> Tensor:
    """``Rᵀ v`` for ``R [3, 3]`` or ``[N, 3, 3]`` and ``v [N, 3]``."""
    return v @ R if R.dim() == 2 else torch.einsum("nji,nj->ni", R, v)


def _to_world(R: Tensor | None, v: Tensor) -> Tensor:
    """``R v`` for ``R`` ``None`` (identity), ``[3, 3]`` or ``[N, 3, 3]`` and ``v [N, 3]``."""
    if R is None:
        return v
    return v @ R.T if R.dim() == 2 else torch.einsum("nij,nj->ni", R, v)


@dataclass
class Hits:
    """Nearest hits of ``N`` rays: distance ``s [N]`` (``inf`` = background), world
    ``normal [N, 3]``, ``albedo [N, 3]`` and ``index [N]`` of the object hit in
    ``scene.objects`` (−1 = none)."""

    s: Tensor
    normal: Tensor
    albedo: Tensor
    index: Tensor

    @staticmethod
    def empty(n: int, dtype: torch.dtype = torch.float64) -> Hits:
        return Hits(torch.full((n,), float("inf"), dtype=dtype), torch.zeros(n, 3, dtype=dtype),
                    torch.zeros(n, 3, dtype=dtype), torch.full((n,), -1, dtype=torch.long))

    def take(self, idx: Tensor) -> Hits:
        """The hits of rays ``idx`` (a copy)."""
        return Hits(self.s[idx], self.normal[idx], self.albedo[idx], self.index[idx])


#: Which primitives :meth:`Renderer.trace` intersects: all, only those that never change
#: (their hits can be cached per ray), or only those that do.
PARTS: tuple[str, ...] = ("all", "static", "moving")


class Renderer:
    """Linear radiance of rays at per-ray times: ``radiance(o, d, t) -> [N, 3]``.

    Per call, the world pose ``x_w = R_w x_l + c_w`` of every node needed is computed
    once for all rays (parents first, memoised). Each box or sphere belongs to a
    *body*: itself if it has its own motion, else its parent group (or the world);
    the boxes (spheres) of the static or of the moving part are tested in one
    :class:`~eventrecon.sim.primitives.BoxSet` (``SphereSet``), with the rays moved
    into each body's frame. Any other primitive (skirt, plane) culls the rays by its
    root ancestor's hull sphere (which holds every descendant at all times), then by
    its own bounding sphere at each ray's time, and is intersected in its own frame.
    Objects whose parent is not in ``scene.objects`` are not rendered (the empty stage
    drops a moving group together with its children).
    """

    def __init__(self, scene: Scene):
        self.scene = scene
        ids = {id(o): i for i, o in enumerate(scene.objects)}
        self._index = ids

        def root(o: SceneObject) -> SceneObject | None:
            while o.parent is not None:
                if id(o.parent) not in ids:
                    return None
                o = o.parent
            return o

        prims = [(o, root(o)) for o in scene.objects if o.kind != "group"]
        prims = [(o, r) for o, r in prims if r is not None]
        self._subject = torch.tensor([not o.in_background for o in scene.objects] + [False])
        # boxes and spheres: one set per kind and part, each member fixed in a body
        self._sets: dict[tuple[str, bool], tuple[BoxSet | SphereSet,
                                                 list[SceneObject | None]]] = {}
        for kind, moving in ((k, m) for k in ("box", "sphere") for m in (False, True)):
            objs = [o for o, _ in prims if o.kind == kind and o.moves == moving]
            if not objs:
                continue
            bodies: list[SceneObject | None] = []
            rows = []
            for o in objs:
                body = o if o.moves_self else o.parent
                if not any(body is x for x in bodies):
                    bodies.append(body)
                own = body is o
                rows.append((np.eye(3) if own else o.orientation,
                             np.zeros(3) if own else o.position,
                             next(i for i, x in enumerate(bodies) if x is body)))
            cls, size = (BoxSet, np.stack([o.half_size for o in objs])) if kind == "box" \
                else (SphereSet, np.array([o.radius for o in objs]))
            self._sets[kind, moving] = (cls(np.stack([r[0] for r in rows]),
                                            np.stack([r[1] for r in rows]), size,
                                            [o.texture for o in objs], [ids[id(o)] for o in objs],
                                            [r[2] for r in rows]), bodies)
        #: whether anything is static (else the cache of static hits is skipped)
        self.has_static = any(not o.moves for o, _ in prims)
        self._others = []     # (primitive, world hull centre, radius; None: no culling)
        for o, r in prims:
            if o.kind not in ("box", "sphere"):
                centre, rad = r.hull()
                self._others.append((o, torch.as_tensor(centre, dtype=torch.float64),
                                     None if o.kind == "plane" else rad))

    def _intersect(self, obj: SceneObject, o: Tensor, d: Tensor, t: Tensor
                   ) -> tuple[Tensor, Tensor, Tensor]:
        """``(s [N], n_local [N, 3], p_local [N, 3])`` of a primitive in its frame."""
        if obj.kind == "sphere":
            s = intersect_sphere(o, d, obj.radius)
            p = o + torch.nan_to_num(s, posinf=0.0)[:, None] * d
            return s, p / obj.radius, p
        if obj.kind == "skirt":
            return intersect_skirt(o, d, t, obj.skirt)
        if obj.kind == "plane":
            s = intersect_plane(o, d, obj.height)
            p = o + torch.nan_to_num(s, posinf=0.0)[:, None] * d
            s = torch.where(p[:, 0] ** 2 + p[:, 2] ** 2 <= obj.radius ** 2, s,
                            torch.full_like(s, float("inf")))
            n = torch.zeros_like(o)
            n[:, 1] = -1.0
            p[:, 1] -= obj.height
            return s, n, p
        s, n = intersect_box(o, d, torch.as_tensor(obj.half_size, dtype=o.dtype,
                                                   device=o.device))
        return s, n, o + torch.nan_to_num(s, posinf=0.0)[:, None] * d

    def _world(self, node: SceneObject, t: Tensor, memo: dict) -> tuple[Tensor, Tensor]:
        """``(R_w, c_w)`` of ``node`` at the rays' times ``t [N]`` (memoised in ``memo``):
        ``R_w`` ``[3, 3]`` or ``[N, 3, 3]``, ``c_w`` ``[1, 3]`` or ``[N, 3]``."""
        key = id(node)
        if key not in memo:
            if node.kind == "plane":
                memo[key] = (torch.eye(3, dtype=t.dtype), torch.zeros(1, 3, dtype=t.dtype))
                return memo[key]
            R, c = node.pose(t if node.moves_self else t[:1])
            if node.parent is not None:
                Rp, cp = self._world(node.parent, t, memo)
                if Rp.dim() == 3 and c.shape[0] == 1:
                    c = c.expand(Rp.shape[0], 3)
                c, R = _to_world(Rp, c) + cp, Rp @ R
            memo[key] = (R, c)
        return memo[key]

    def _frame(self, obj: SceneObject, t: Tensor, idx: Tensor, o: Tensor, d: Tensor,
               memo: dict) -> tuple[Tensor, Tensor, Tensor]:
        """Of rays ``idx``, those that meet ``obj``'s bounding sphere about its origin at
        their own times, with ``obj``'s world pose for them: ``(idx [n], R_w, c_w)``
        (``R_w`` ``[3, 3]`` or ``[n, 3, 3]``, ``c_w`` ``[1, 3]`` or ``[n, 3]``)."""
        if obj.kind == "plane":
            return idx, torch.eye(3, dtype=o.dtype), torch.zeros(1, 3, dtype=o.dtype)
        ti = t[idx]
        R, c = obj.pose(ti if obj.moves_self else ti[:1])
        Rp = None
        if obj.parent is not None:
            Rp, cp = self._world(obj.parent, t, memo)
            Rp = Rp[idx] if Rp.dim() == 3 else Rp
            cp = cp[idx] if cp.shape[0] > 1 else cp
            if Rp.dim() == 3 and c.shape[0] == 1:
                c = c.expand(idx.numel(), 3)
            c = _to_world(Rp, c) + cp
        k = intersect_sphere(o[idx] - c, d[idx], obj.bound_radius + 1e-6).isfinite()
        k = k.nonzero()[:, 0]
        c = c[k] if c.shape[0] > 1 else c
        R = R[k] if R.dim() == 3 else R
        if Rp is not None:
            R = (Rp[k] if Rp.dim() == 3 else Rp) @ R
        return idx[k], R, c

    @staticmethod
    def _wanted(part: str, moving: bool) -> bool:
        return part == "all" or (part == "moving") == moving

    def _update(self, hits: Hits, idx: Tensor, s: Tensor, n: Tensor, alb: Tensor,
                index: Tensor | int) -> None:
        """Keep the hits ``s, n, alb`` of rays ``idx`` that are nearer than ``hits``."""
        win = s < hits.s[idx]
        if bool(win.any()):
            w = idx[win]
            hits.s[w], hits.normal[w], hits.albedo[w] = s[win], n[win], alb[win]
            hits.index[w] = index[win] if isinstance(index, Tensor) else index

    def _trace_set(self, key: tuple[str, bool], o: Tensor, d: Tensor, t: Tensor, hits: Hits,
                   memo: dict) -> None:
        bset, bodies = self._sets[key]
        poses = [None if b is None else self._world(b, t, memo) for b in bodies]
        ob = torch.stack([o if p is None else _to_local(p[0], o - p[1]) for p in poses], 1)
        db = torch.stack([d if p is None else _to_local(p[0], d) for p in poses], 1)
        s, k, n, alb = bset.intersect(ob, db)
        idx = torch.isfinite(s).nonzero()[:, 0]
        if not idx.numel():
            return
        kw = k[idx]
        nw = n[idx]
        body = bset.body[kw]
        for i, p in enumerate(poses):
            rows = (body == i).nonzero()[:, 0]
            if p is not None and rows.numel():
                R = p[0][idx[rows]] if p[0].dim() == 3 else p[0]
                nw[rows] = _to_world(R, nw[rows])
        self._update(hits, idx, s[idx], nw, alb[idx], bset.ids[kw])

    def trace(self, o: Tensor, d: Tensor, t: Tensor, part: str = "all",
              init: Hits | None = None) -> Hits:
        """Nearest hits of rays ``o, d [N, 3]`` (unit ``d``, float64) at times ``t [N]``.

        ``part``: which primitives to intersect (:data:`PARTS`); ``init``: hits to start
        from (updated in place), e.g. the cached hits of the static part.
        """
        if part not in PARTS:
            raise ValueError(f"part: expected one of {PARTS}, got {part!r}")
        hits = init if init is not None else Hits.empty(o.shape[0], o.dtype)
        memo: dict = {}
        for key in self._sets:
            if self._wanted(part, key[1]):
                self._trace_set(key, o, d, t, hits, memo)
        for obj, centre, rad in self._others:
            if not self._wanted(part, obj.moves):
                continue
            if rad is None:
                idx = torch.arange(o.shape[0], device=o.device)
            else:
                idx = intersect_sphere(o - centre.to(o), d, rad + 1e-6).isfinite().nonzero()[:, 0]
            if not idx.numel():
                continue
            idx, R, c = self._frame(obj, t, idx, o, d, memo)
            if not idx.numel():
                continue
            s, nl, p = self._intersect(obj, _to_local(R, o[idx] - c), _to_local(R, d[idx]),
                                       t[idx])
            self._update(hits, idx, s, _to_world(R, nl), obj.texture.albedo(p),
                         self._index[id(obj)])
        return hits

    def shade(self, h: Hits) -> Tensor:
        """``[N, 3]`` float64 linear radiance of hits (formula in
        :mod:`eventrecon.sim.scene`; the background where nothing is hit)."""
        sc = self.scene
        dt, dev = h.normal.dtype, h.normal.device
        lt = torch.as_tensor(sc.light.direction, dtype=dt, device=dev)
        shade = sc.light.ambient + sc.light.intensity * (h.normal @ lt).clamp_min(0)
        rgb = h.albedo * shade[:, None] * torch.as_tensor(sc.light.color, dtype=dt, device=dev)
        bg = torch.as_tensor(sc.background, dtype=dt, device=dev)
        return torch.where(h.s.isfinite()[:, None], rgb, bg.expand(h.s.shape[0], 3))

    def is_subject(self, h: Hits) -> Tensor:
        """``[N]`` bool: whether each nearest hit is a subject (an object the background
        images leave out: moving, or marked ``subject``)."""
        return self._subject.to(h.index.device)[h.index]

    def radiance(self, o: Tensor, d: Tensor, t: Tensor) -> Tensor:
        """Shade rays ``o, d [N, 3]`` (unit ``d``) at normalised times ``t [N]``.

        Returns:
            ``[N, 3]`` float64 linear radiance (formula in :mod:`eventrecon.sim.scene`).
        """
        if o.shape[0] > CHUNK:
            return torch.cat([self.radiance(o[i:i + CHUNK], d[i:i + CHUNK], t[i:i + CHUNK])
                              for i in range(0, o.shape[0], CHUNK)])
        return self.shade(self.trace(o.double(), d.double(), t.double()))

    def subject(self, o: Tensor, d: Tensor, t: Tensor) -> Tensor:
        """``[N]`` bool: whether the nearest hit of each ray is a subject
        (:meth:`is_subject`)."""
        return self.is_subject(self.trace(o.double(), d.double(), t.double()))
