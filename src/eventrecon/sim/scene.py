"""Procedural scenes: analytic primitives with textures and motions, a light, a backdrop.

A scene config (``conf/scene/*.yaml``) lists ``objects``; each has a ``type``
(``sphere`` with ``radius``; ``box`` with full edge lengths ``size [3]`` and an optional
fixed ``orientation {axis, deg}``; ``plane``, a static ground disc at world
``y = height`` of optional ``radius`` about the y axis, whose normal points up, i.e.
towards −y), a ``position [3]``, a
``texture`` (:mod:`eventrecon.sim.texture`) and a ``motion`` (:mod:`eventrecon.sim.motion`;
one mapping or a list). Lighting is Lambertian under one directional light, no shadows:

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

from eventrecon.errors import InputError
from eventrecon.sim.config import get, get_vec
from eventrecon.sim.motion import Motion, parse_motions, rotation_matrices
from eventrecon.sim.texture import Texture, parse_texture

__all__ = ["SceneObject", "Light", "Scene", "parse_scene", "PRIMITIVES"]

log = logging.getLogger(__name__)

PRIMITIVES: tuple[str, ...] = ("sphere", "box", "plane")


@dataclass
class SceneObject:
    """One primitive: geometry parameters, base pose, texture and motion terms.

    Attributes:
        kind: ``sphere`` | ``box`` | ``plane``.
        radius: sphere radius (plane: disc radius); half_size: ``[3]`` box half-extents;
            height: plane y.
        position: ``[3]`` base centre ``c_0``; orientation: ``[3, 3]`` fixed rotation ``R_0``.
        subject: part of what is reconstructed even when it does not move, so it is left
            out of the background images (YAML ``subject: true``); moving objects always are.
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

    @property
    def moves(self) -> bool:
        return any(m.moves for m in self.motions)

    @property
    def in_background(self) -> bool:
        """Whether the background images (the empty stage) show this object."""
        return not (self.moves or self.subject)

    @property
    def bound_radius(self) -> float:
        """Radius of a sphere about the object's centre that contains it."""
        return self.radius if self.kind == "sphere" else float(np.linalg.norm(self.half_size))

    def hull(self) -> tuple[np.ndarray, float]:
        """A sphere ``(centre [3], radius)`` containing the object at every ``t ∈ [0, 1]``."""
        return self.position, self.bound_radius + sum(m.max_extent() for m in self.motions)

    def pose(self, t: Tensor) -> tuple[Tensor, Tensor]:
        """``(R, c [N, 3])`` with ``x_world = R x_local + c`` at times ``t [N]``;
        ``R`` is ``[3, 3]`` when it does not change over time, else ``[N, 3, 3]``."""
        n = t.shape[0]
        c = torch.as_tensor(self.position, dtype=t.dtype, device=t.device).expand(n, 3)
        R = torch.as_tensor(self.orientation, dtype=t.dtype, device=t.device)
        for m in self.motions:
            if m.kind not in ("static", "spin"):
                c = c + m.displacement(t)
            Rm = m.rotation(t)
            if Rm is not None:
                R = Rm @ R
        return R, c

    def interval_spheres(self, n: int, sub: int = 32) -> tuple[np.ndarray, np.ndarray]:
        """Spheres containing the object over each of ``n`` equal time intervals.

        Returns:
            ``(centres [n, 3], radii [n])``: centre = object centre at the interval's
            midpoint, radius = bound radius + the largest distance of the centre from it
            over ``sub`` samples of the interval + the largest step between samples
            (so the sphere is conservative between samples too).
        """
        t = torch.linspace(0, 1, n * sub + 1, dtype=torch.float64)
        c = self.pose(t)[1].numpy()
        step = float(np.linalg.norm(np.diff(c, axis=0), axis=1).max()) if len(c) > 1 else 0.0
        mids = self.pose(torch.linspace(0.5 / n, 1 - 0.5 / n, n, dtype=torch.float64))[1].numpy()
        idx = np.arange(n)[:, None] * sub + np.arange(sub + 1)[None]          # [n, sub+1]
        spread = np.linalg.norm(c[idx] - mids[:, None], axis=-1).max(1)
        return mids, self.bound_radius + spread + step + 1e-9


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
    """Objects, light and background colour of a procedural scene."""

    objects: list[SceneObject]
    light: Light
    background: np.ndarray

    @property
    def moving(self) -> list[SceneObject]:
        return [o for o in self.objects if o.moves]

    def cylinder_violation(self, radius: float, y_min: float, y_max: float,
                           n_t: int = 501) -> float:
        """Largest distance by which a bounding sphere of a non-plane object leaves the
        clipping cylinder ``x²+z² ≤ r², y ∈ [y_min, y_max]`` over ``n_t`` times (0 = inside)."""
        t = torch.linspace(0, 1, n_t, dtype=torch.float64)
        worst = 0.0
        for o in self.objects:
            if o.kind == "plane":
                continue
            c = o.pose(t)[1].numpy()
            b = o.bound_radius
            out = np.maximum.reduce([np.hypot(c[:, 0], c[:, 2]) + b - radius,
                                     y_min - (c[:, 1] - b), c[:, 1] + b - y_max])
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


def parse_object(raw: Mapping, where: str, pre: str) -> SceneObject:
    """Parse one entry of ``objects``."""
    kind = get(raw, "type", str, where, pre, check=lambda v: v in PRIMITIVES,
               expect="one of " + ", ".join(PRIMITIVES))
    tex = parse_texture(raw.get("texture"), where, f"{pre}texture.")
    motions = parse_motions(raw.get("motion"), where, f"{pre}motion")
    if kind == "plane":
        if any(m.moves for m in motions):
            raise InputError(where, f"{pre}motion", "a static ground plane (no motion)",
                             [m.kind for m in motions])
        h = get(raw, "height", float, where, pre)
        r = get(raw, "radius", float, where, pre, default=float("inf"), check=lambda v: v > 0,
                expect="a disc radius > 0")
        return SceneObject(kind, np.array([0.0, h, 0.0]), tex, [], radius=r, height=h)
    pos = get_vec(raw, "position", 3, where, pre, default=(0.0, -0.25, 0.0))
    ori = _orientation(raw.get("orientation"), where, f"{pre}orientation.")
    subject = get(raw, "subject", bool, where, pre, default=False)
    if kind == "sphere":
        r = get(raw, "radius", float, where, pre, check=lambda v: v > 0, expect="a radius > 0")
        return SceneObject(kind, pos, tex, motions, radius=r, orientation=ori, subject=subject)
    size = get_vec(raw, "size", 3, where, pre)
    if np.any(size <= 0):
        raise InputError(where, f"{pre}size", "three edge lengths > 0", size.tolist())
    return SceneObject(kind, pos, tex, motions, half_size=size / 2, orientation=ori,
                       subject=subject)


def parse_scene(cfg: Mapping, where: str) -> Scene:
    """Build a :class:`Scene` from the ``objects``, ``light``, ``background`` fields."""
    objs_raw = get(cfg, "objects", list, where, default=[], expect="a list of objects")
    objects = [parse_object(o, where, f"objects[{i}].") for i, o in enumerate(objs_raw)]
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
