"""Procedural scenes: analytic primitives with textures and motions, a light, a backdrop.

A scene config (``conf/scene/*.yaml``) lists ``objects``; each has a ``type``:

- ``sphere`` with ``radius``; ``box`` with full edge lengths ``size [3]``;
- ``skirt``: a non-rigidly deforming sheet with exact intersection
  (:mod:`eventrecon.sim.skirt`);
- ``plane``: a static ground disc at world ``y = height`` of optional ``radius`` about the
  y axis, whose normal points up, i.e. towards −y;
- ``group``: no geometry -- a joint or rigid assembly. Objects naming it as their
  ``parent`` have their ``position``, ``orientation`` and ``motion`` in its frame, so its
  own motion carries them all (a rotation turns them about the group's origin, the
  joint). A parent must be listed before its children (the tree has no cycles).

and a ``position [3]`` (default ``[0, −0.25, 0]``, ``[0, 0, 0]`` for a child), an
optional fixed ``orientation {axis, deg}``, a ``texture`` (:mod:`eventrecon.sim.texture`),
a ``motion`` (:mod:`eventrecon.sim.motion`; one mapping or a list), an optional ``name``
and ``parent``, and ``subject`` (inherited by children). The world pose of an object is
the composition along its parents,

.. math:: x_w = R_p(t)\\,\\big(R(t)\\,x_l + c(t)\\big) + c_p(t).

Lighting is Lambertian under one directional light, no shadows:

.. math:: I = a \\odot \\big(k_a + k_d\\max(0, n\\cdot\\hat l)\\big)\\,c_l,

``a`` the texture albedo, ``k_a = light.ambient``, ``k_d = light.intensity``,
``\\hat l`` the unit ``light.direction`` (towards the light), ``c_l = light.color``.
Rays that hit nothing see the constant ``background`` colour (linear).

Without shadows a pixel's radiance changes only when its ray meets a moving object, so
anything static (a ground plane outside the clipping cylinder included) is fully
explained by the per-view background frame.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from eventrecon.common.errors import InputError
from eventrecon.sim.config import get, get_vec
from eventrecon.sim.motion import Motion, parse_motions, rotation_matrices
from eventrecon.sim.skirt import Skirt, parse_skirt
from eventrecon.sim.texture import Texture, parse_texture

__all__ = ["SceneObject", "Light", "Scene", "parse_scene", "parse_object", "PRIMITIVES"]

log = logging.getLogger(__name__)

PRIMITIVES: tuple[str, ...] = ("sphere", "box", "skirt", "plane", "group")

#: Box corners in units of the half-extents, ``[8, 3]``.
_CORNERS = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)


@dataclass(eq=False)
class SceneObject:
    """One node: geometry parameters, base pose, texture, motion terms and parent.

    Attributes:
        kind: one of :data:`PRIMITIVES`.
        radius: sphere radius (plane: disc radius); half_size: ``[3]`` box half-extents;
            height: plane y; skirt: the :class:`~eventrecon.sim.skirt.Skirt`.
        position: ``[3]`` base centre ``c_0``; orientation: ``[3, 3]`` fixed rotation ``R_0``
            (both in the parent's frame).
        subject: part of what is reconstructed even when it does not move, so it is left
            out of the background images (YAML ``subject: true``, inherited by children);
            moving objects always are.
        name, parent: the node's name and its parent group (``None``: the world).
        group_radius: for a group, the radius about its origin containing every
            descendant at all times (set by :func:`parse_scene`).
    """

    kind: str
    position: np.ndarray
    texture: Texture
    motions: list[Motion] = field(default_factory=list)
    radius: float = 0.0
    half_size: np.ndarray | None = None
    height: float = 0.0
    orientation: np.ndarray = field(default_factory=lambda: np.eye(3))
    subject: bool = False
    skirt: Skirt | None = None
    name: str | None = None
    parent: SceneObject | None = None
    group_radius: float = 0.0

    @property
    def moves_self(self) -> bool:
        """Whether its own pose (relative to the parent) changes over time."""
        return any(m.moves for m in self.motions)

    @property
    def moves(self) -> bool:
        """Whether its world shape changes: own motion, a moving parent or deformation."""
        return (self.moves_self or (self.skirt is not None and self.skirt.deforms)
                or (self.parent is not None and self.parent.moves))

    @property
    def in_background(self) -> bool:
        """Whether the background images (the empty stage) show this object."""
        return not (self.moves or self.subject)

    @property
    def bound_radius(self) -> float:
        """Radius of a sphere about the object's origin that contains it at all times."""
        if self.kind == "sphere":
            return self.radius
        if self.kind == "box":
            return float(np.linalg.norm(self.half_size))
        if self.kind == "skirt":
            return self.skirt.bound_radius()
        if self.kind == "plane":
            return float("inf")
        return self.group_radius

    def hull(self) -> tuple[np.ndarray, float]:
        """A sphere ``(centre [3], radius)`` in the parent's frame containing the object
        (a group: its descendants) at every ``t ∈ [0, 1]``."""
        return self.position, self.bound_radius + sum(m.max_extent() for m in self.motions)

    def pose(self, t: Tensor) -> tuple[Tensor, Tensor]:
        """``(R, c [N, 3])`` with ``x_parent = R x_local + c`` at times ``t [N]``;
        ``R`` is ``[3, 3]`` when it does not change over time, else ``[N, 3, 3]``."""
        n = t.shape[0]
        c = torch.as_tensor(self.position, dtype=t.dtype, device=t.device).expand(n, 3)
        R = None if np.array_equal(self.orientation, np.eye(3)) else \
            torch.as_tensor(self.orientation, dtype=t.dtype, device=t.device)
        for m in self.motions:
            if m.translates:
                c = c + m.displacement(t)
            Rm = m.rotation(t)
            if Rm is not None:
                R = Rm if R is None else Rm @ R
        return (torch.eye(3, dtype=t.dtype, device=t.device) if R is None else R), c

    def world_pose(self, t: Tensor, memo: dict | None = None) -> tuple[Tensor, Tensor]:
        """``(R [N, 3, 3], c [N, 3])`` with ``x_world = R x_local + c``: the poses of the
        parents composed (module docstring). ``memo``: a dict reused across calls with
        the same ``t`` (parents are then composed once)."""
        if memo is not None and id(self) in memo:
            return memo[id(self)]
        R, c = self.pose(t)
        R = R.expand(t.shape[0], 3, 3) if R.dim() == 2 else R
        if self.parent is not None:
            Rp, cp = self.parent.world_pose(t, memo)
            R, c = Rp @ R, torch.einsum("nij,nj->ni", Rp, c) + cp
        if memo is not None:
            memo[id(self)] = (R, c)
        return R, c

    def support_points(self, t: Tensor, memo: dict | None = None) -> tuple[Tensor, Tensor]:
        """World points whose extremes bound the object's radial distance from the y axis
        and its height at times ``t [T]``: ``(points [T, P, 3], pad [P])`` -- the object
        lies within ``pad`` of their convex hull (box: its 8 corners, pad 0; sphere: the
        centre, pad r; skirt: its rings, pad = the sampling margin); ``memo`` as in
        :meth:`world_pose`."""
        R, c = self.world_pose(t, memo)
        if self.kind == "box":
            local = torch.as_tensor(_CORNERS * self.half_size, dtype=t.dtype)
            pts = torch.einsum("tij,pj->tpi", R, local) + c[:, None]
            return pts, torch.zeros(8, dtype=t.dtype)
        if self.kind == "skirt":
            local, margin = self.skirt.ring_points(t)
            pts = torch.einsum("tij,tpj->tpi", R, local) + c[:, None]
            return pts, torch.full((pts.shape[1],), margin, dtype=t.dtype)
        return c[:, None], torch.full((1,), self.bound_radius, dtype=t.dtype)

    def still_intervals(self, n: int) -> np.ndarray:
        """``[n]`` bool: whether the object's world shape is constant over each interval
        ``[k/n, (k+1)/n]`` (no motion of it or of a parent changes there, and it does
        not deform)."""
        if self.skirt is not None and self.skirt.deforms:
            return np.zeros(n, bool)
        still = np.ones(n, bool)
        for m in self.motions:
            still &= m.constant_intervals(n)
        return still if self.parent is None else still & self.parent.still_intervals(n)

    def bound_spheres(self) -> tuple[np.ndarray, np.ndarray]:
        """Local spheres ``(centres [m, 3], radii [m])`` whose union contains the object:
        one about the origin (:attr:`bound_radius`), but a box is cut into ``m`` nearly
        cubic sub-boxes (cells at least a quarter of its longest edge), each in its own
        sphere, so that a long or flat part is covered tightly, and a skirt has one
        sphere per band (:meth:`~eventrecon.sim.skirt.Skirt.band_spheres`)."""
        if self.kind == "skirt":
            return self.skirt.band_spheres()
        if self.kind != "box":
            return np.zeros((1, 3)), np.array([self.bound_radius])
        size = 2 * self.half_size
        cell = max(size.min(), size.max() / 4)
        n = np.maximum(1, np.ceil(size / cell - 1e-9)).astype(int)
        axes = [(np.arange(k) + 0.5) / k * s - s / 2 for k, s in zip(n, size)]
        centres = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        return centres, np.full(len(centres), float(np.linalg.norm(size / n / 2)))

    def interval_bounds(self, n: int, sub: int = 32, memos: tuple[dict, dict] | None = None
                        ) -> tuple[np.ndarray, np.ndarray]:
        """Spheres containing the object over each of ``n`` equal time intervals, one
        per sphere of :meth:`bound_spheres`.

        Returns:
            ``(centres [m, n, 3], radii [m, n])``: centre = the local sphere's centre
            (world) at the interval's midpoint, radius = its radius + the largest
            distance of the centre from there over ``sub`` samples of the interval + the
            largest step between samples (so the sphere is conservative between samples
            too); radius −1 where the object is at rest over the whole interval
            (:meth:`still_intervals`). ``memos``: two dicts shared by calls with the same
            ``n`` and ``sub`` (world poses of common parents are composed once).
        """
        return self._intervals(*self.bound_spheres(), n, sub, memos)

    def interval_spheres(self, n: int, sub: int = 32) -> tuple[np.ndarray, np.ndarray]:
        """One sphere about the object's origin per interval: ``(centres [n, 3],
        radii [n])`` as :meth:`interval_bounds` with the single sphere of
        :attr:`bound_radius`."""
        c, r = self._intervals(np.zeros((1, 3)), np.array([self.bound_radius]), n, sub)
        return c[0], r[0]

    def _intervals(self, local: np.ndarray, rad: np.ndarray, n: int, sub: int,
                   memos: tuple[dict, dict] | None = None) -> tuple[np.ndarray, np.ndarray]:
        t = torch.linspace(0, 1, n * sub + 1, dtype=torch.float64)
        tm = torch.linspace(0.5 / n, 1 - 0.5 / n, n, dtype=torch.float64)
        L = torch.as_tensor(local)
        m0, m1 = memos if memos is not None else (None, None)
        c, mids = ((torch.einsum("tij,mj->mti", R, L) + x[None]).numpy()
                   for R, x in (self.world_pose(t, m0), self.world_pose(tm, m1)))  # [m, T, 3]
        step = np.linalg.norm(np.diff(c, axis=1), axis=-1).max(1) if c.shape[1] > 1 \
            else np.zeros(len(rad))
        idx = np.arange(n)[:, None] * sub + np.arange(sub + 1)[None]          # [n, sub+1]
        spread = np.linalg.norm(c[:, idx] - mids[:, :, None], axis=-1).max(-1)  # [m, n]
        still = self.still_intervals(n)
        radii = rad[:, None] + spread + step[:, None] + 1e-9
        return mids, np.where(still[None], -1.0, radii)


@dataclass
class Light:
    """Directional light: unit ``direction [3]`` towards the light, ``ambient``,
    ``intensity`` (diffuse gain) and ``color [3]``."""

    direction: np.ndarray
    ambient: float = 0.3
    intensity: float = 0.7
    color: np.ndarray = field(default_factory=lambda: np.ones(3))


@dataclass
class Scene:
    """Objects (parents before children), light and background colour of a scene."""

    objects: list[SceneObject]
    light: Light
    background: np.ndarray

    @property
    def moving(self) -> list[SceneObject]:
        """The objects with geometry whose world shape changes over time."""
        return [o for o in self.objects if o.kind != "group" and o.moves]

    def cylinder_violation(self, radius: float, y_min: float, y_max: float,
                           n_t: int = 501) -> float:
        """Largest distance by which an object (every kind but planes and groups) leaves
        the clipping cylinder ``x²+z² ≤ r², y ∈ [y_min, y_max]`` over ``n_t`` times
        (0 = inside), from :meth:`SceneObject.support_points`."""
        t = torch.linspace(0, 1, n_t, dtype=torch.float64)
        worst, memo = 0.0, {}
        for o in self.objects:
            if o.kind in ("plane", "group"):
                continue
            p, pad = (x.numpy() for x in o.support_points(t, memo))
            out = np.maximum.reduce([np.hypot(p[..., 0], p[..., 2]) + pad - radius,
                                     y_min - (p[..., 1] - pad), p[..., 1] + pad - y_max])
            worst = max(worst, float(out.max()))
        return worst


def _orientation(raw: Mapping | None, where: str, pre: str) -> np.ndarray:
    if raw is None:
        return np.eye(3)
    axis = get_vec(raw, "axis", 3, where, pre)
    deg = get(raw, "deg", float, where, pre)
    if np.linalg.norm(axis) == 0:
        raise InputError(where, f"{pre}axis", "a non-zero vector", axis.tolist())
    return rotation_matrices(torch.as_tensor(axis), torch.tensor([math.radians(deg)],
                                                                dtype=torch.float64))[0].numpy()


def parse_object(raw: Mapping, where: str, pre: str,
                 named: Mapping[str, SceneObject] | None = None) -> SceneObject:
    """Parse one entry of ``objects``; ``named``: the groups listed before it, by name."""
    kind = get(raw, "type", str, where, pre, check=lambda v: v in PRIMITIVES,
               expect="one of " + ", ".join(PRIMITIVES))
    motions = parse_motions(raw.get("motion"), where, f"{pre}motion")
    name = get(raw, "name", str, where, pre, default=None)
    pname = get(raw, "parent", str, where, pre, default=None)
    parent = None
    if pname is not None:
        groups = dict(named or {})
        if kind == "plane":
            raise InputError(where, f"{pre}parent",
                             "no parent (a ground plane belongs to the world)", pname)
        if pname not in groups:
            raise InputError(where, f"{pre}parent", "the name of a group listed earlier ("
                             + (", ".join(groups) or "none so far") + ")", repr(pname))
        parent = groups[pname]
    if kind == "plane":
        if any(m.moves for m in motions):
            raise InputError(where, f"{pre}motion", "a static ground plane (no motion)",
                             [m.kind for m in motions])
        h = get(raw, "height", float, where, pre)
        r = get(raw, "radius", float, where, pre, default=float("inf"), check=lambda v: v > 0,
                expect="a disc radius > 0")
        tex = parse_texture(raw.get("texture"), where, f"{pre}texture.")
        return SceneObject(kind, np.array([0.0, h, 0.0]), tex, [], radius=r, height=h,
                           name=name)
    pos = get_vec(raw, "position", 3, where, pre,
                  default=(0.0, -0.25, 0.0) if parent is None else (0.0, 0.0, 0.0))
    ori = _orientation(raw.get("orientation"), where, f"{pre}orientation.")
    subject = get(raw, "subject", bool, where, pre, default=False) or \
        (parent is not None and parent.subject)
    tex = parse_texture(raw.get("texture"), where, f"{pre}texture.")
    common = dict(orientation=ori, subject=subject, name=name, parent=parent)
    if kind == "group":
        return SceneObject(kind, pos, tex, motions, **common)
    if kind == "skirt":
        return SceneObject(kind, pos, tex, motions, skirt=parse_skirt(raw, where, pre), **common)
    if kind == "sphere":
        r = get(raw, "radius", float, where, pre, check=lambda v: v > 0, expect="a radius > 0")
        return SceneObject(kind, pos, tex, motions, radius=r, **common)
    size = get_vec(raw, "size", 3, where, pre)
    if np.any(size <= 0):
        raise InputError(where, f"{pre}size", "three edge lengths > 0", size.tolist())
    return SceneObject(kind, pos, tex, motions, half_size=size / 2, **common)


def parse_scene(cfg: Mapping, where: str) -> Scene:
    """Build a :class:`Scene` from the ``objects``, ``light``, ``background`` fields."""
    objs_raw = get(cfg, "objects", list, where, default=[], expect="a list of objects")
    objects: list[SceneObject] = []
    groups: dict[str, SceneObject] = {}
    for i, o in enumerate(objs_raw):
        obj = parse_object(o, where, f"objects[{i}].", groups)
        if obj.name is not None:
            if any(x.name == obj.name for x in objects):
                raise InputError(where, f"objects[{i}].name", "a name no other object has",
                                 obj.name)
            if obj.kind == "group":
                groups[obj.name] = obj
        objects.append(obj)
    for g in reversed(objects):  # children come after their parents: bottom-up radii
        if g.kind == "group":
            g.group_radius = max([float(np.linalg.norm(c.position)) + c.hull()[1]
                                  for c in objects if c.parent is g], default=0.0)
    lraw = get(cfg, "light", Mapping, where, default={}, expect="a mapping")
    direction = get_vec(lraw, "direction", 3, where, "light.", default=(0.3, -1.0, 0.5))
    if np.linalg.norm(direction) == 0:
        raise InputError(where, "light.direction", "a non-zero vector", direction.tolist())
    light = Light(direction / np.linalg.norm(direction),
                  get(lraw, "ambient", float, where, "light.", default=0.3),
                  get(lraw, "intensity", float, where, "light.", default=0.7),
                  get_vec(lraw, "color", 3, where, "light.", default=(1.0, 1.0, 1.0)))
    bg = get_vec(cfg, "background", 3, where, default=(0.353, 0.353, 0.353))
    if np.any(bg < 0) or np.any(bg > 1):
        raise InputError(where, "background", "linear RGB in [0, 1]", bg.tolist())
    return Scene(objects, light, bg)
