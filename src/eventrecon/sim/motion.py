"""Rigid motions of scene objects over normalised time ``t ∈ [0, 1]``.

An object's pose at time ``t`` maps object-local points to the world,

.. math:: x_w = R(t)\\,x_l + c(t),\\qquad c(t) = c_0 + \\sum_m d_m(t),\\quad
          R(t) = \\prod_m R_m(t),

with ``c_0`` the object's ``position`` and one displacement ``d_m`` / rotation ``R_m``
per listed motion (applied in list order). World up is −y.

======== ==================================== ==========================================
type     parameters                           displacement / rotation
======== ==================================== ==========================================
static   –                                    ``d = 0``
linear   ``to [3]``                           ``d = t·to``
orbit    ``radius, turns, phase_deg``         ``d = r(sin φ, 0, cos φ)``, ``φ = φ0 + 2π·turns·t``
                                              (``position`` is the orbit centre)
bounce   ``height, bounces``                  ``d = (0, −h|sin(π·bounces·t)|, 0)``
spin     ``axis [3], turns, phase_deg``       ``R = rot(axis, φ0 + 2π·turns·t)``
keyframe ``keys [[t, dx, dy, dz(, deg)], …]`` piecewise-linear ``d`` (and angle about
         ``axis``)                            ``axis``), held constant outside the keys
======== ==================================== ==========================================
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from eventrecon.common.errors import InputError
from eventrecon.sim.config import get, get_vec

__all__ = ["Motion", "rotation_matrices", "parse_motions", "MOTIONS"]


def rotation_matrices(axis: Tensor, angle: Tensor) -> Tensor:
    """Rodrigues' formula: ``[N, 3, 3]`` rotations by ``angle [N]`` about unit ``axis [3]``.

    ``R = I + sin a·[k]× + (1 − cos a)·[k]×²``.

    >>> R = rotation_matrices(torch.tensor([0., 1., 0.], dtype=torch.float64),
    ...                       torch.tensor([math.pi / 2], dtype=torch.float64))
    >>> torch.allclose(R[0] @ torch.tensor([1., 0., 0.], dtype=torch.float64),
    ...                torch.tensor([0., 0., -1.], dtype=torch.float64))
    True
    """
    kx, kx2 = _cross_matrices(tuple((axis / axis.norm()).tolist()))
    kx, kx2 = kx.to(angle), kx2.to(angle)
    s, c = torch.sin(angle)[:, None, None], torch.cos(angle)[:, None, None]
    eye = torch.eye(3, dtype=angle.dtype, device=angle.device)
    return eye + s * kx + (1 - c) * kx2


@functools.lru_cache(maxsize=256)
def _cross_matrices(k: tuple[float, float, float]) -> tuple[Tensor, Tensor]:
    """``([k]×, [k]×²)`` (float64) of a unit axis, cached per axis."""
    kx = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]],
                      dtype=torch.float64)
    return kx, kx @ kx


@dataclass
class Motion:
    """One motion term: ``displacement(t) -> [N, 3]``, ``rotation(t) -> [N, 3, 3] | None``.

    ``kind`` is one of :data:`MOTIONS`; ``p`` holds its parsed parameters.
    """

    kind: str
    p: dict

    def displacement(self, t: Tensor) -> Tensor:
        """``[N, 3]`` displacement at normalised times ``t [N]`` (float64)."""
        z = torch.zeros(t.shape[0], 3, dtype=t.dtype, device=t.device)
        if self.kind == "linear":
            return t[:, None] * torch.as_tensor(self.p["to"], dtype=t.dtype, device=t.device)
        if self.kind == "orbit":
            phi = math.radians(self.p["phase_deg"]) + 2 * math.pi * self.p["turns"] * t
            z[:, 0], z[:, 2] = self.p["radius"] * torch.sin(phi), self.p["radius"] * torch.cos(phi)
            return z
        if self.kind == "bounce":
            z[:, 1] = -self.p["height"] * torch.sin(math.pi * self.p["bounces"] * t).abs()
            return z
        if self.kind == "keyframe":
            keys = self.p["keys"]
            if not np.any(keys[:, 1:4]):
                return z
            return _interp(t, keys[:, 0], keys[:, 1:4])
        return z

    def rotation(self, t: Tensor) -> Tensor | None:
        """``[N, 3, 3]`` rotation at times ``t [N]``, or ``None`` for the identity."""
        if self.kind == "spin":
            ang = math.radians(self.p["phase_deg"]) + 2 * math.pi * self.p["turns"] * t
        elif self.kind == "keyframe" and self.p["keys"].shape[1] == 5:
            ang = torch.deg2rad(_interp(t, self.p["keys"][:, 0], self.p["keys"][:, 4:5])[:, 0])
        else:
            return None
        return rotation_matrices(torch.as_tensor(self.p["axis"], dtype=t.dtype, device=t.device),
                                 ang)

    def max_extent(self) -> float:
        """Upper bound of ``|d(t)|`` over ``t ∈ [0, 1]`` (for bounding volumes)."""
        if self.kind == "linear":
            return float(np.linalg.norm(self.p["to"]))
        if self.kind == "orbit":
            return float(self.p["radius"])
        if self.kind == "bounce":
            return float(self.p["height"])
        if self.kind == "keyframe":
            return float(np.linalg.norm(self.p["keys"][:, 1:4], axis=1).max())
        return 0.0

    def constant_intervals(self, n: int) -> np.ndarray:
        """``[n]`` bool: whether ``d`` and ``R`` are constant over each closed interval
        ``[k/n, (k+1)/n]`` (exact: a keyframe track is constant there iff its values at
        both ends and at every key inside agree).

        >>> m = parse_motions({"type": "keyframe", "keys": [[0, 0, 0, 0], [0.5, 1, 0, 0],
        ...                                                 [0.75, 1, 0, 0]]}, "s", "m")[0]
        >>> m.constant_intervals(4).tolist()
        [False, False, True, True]
        """
        if not self.moves:
            return np.ones(n, bool)
        if self.kind != "keyframe":
            return np.zeros(n, bool)
        keys = self.p["keys"]
        edges = np.arange(n + 1) / n
        vals = np.stack([np.interp(edges, keys[:, 0], keys[:, i])
                         for i in range(1, keys.shape[1])], -1)                # [n+1, C]
        const = np.all(vals[1:] == vals[:-1], axis=-1)
        for tk, vk in zip(keys[:, 0], keys[:, 1:]):
            k = int(np.floor(tk * n))
            if 0 <= k < n and edges[k] < tk < edges[k + 1]:
                const[k] &= bool(np.all(vk == vals[k]))
        return const

    @property
    def translates(self) -> bool:
        """Whether the displacement ``d`` is ever non-zero."""
        if self.kind == "linear":
            return bool(np.any(self.p["to"]))
        if self.kind in ("orbit", "bounce"):
            return self.p["radius" if self.kind == "orbit" else "height"] != 0
        return self.kind == "keyframe" and bool(np.any(self.p["keys"][:, 1:4]))

    @property
    def moves(self) -> bool:
        """Whether the pose changes over time at all."""
        if self.kind == "keyframe":
            keys = self.p["keys"][:, 1:]
            return bool(np.any(keys != keys[0]))
        return self.kind != "static" and not (self.kind in ("orbit", "spin") and
                                              self.p["turns"] == 0)


def _interp(t: Tensor, tk: np.ndarray, vk: np.ndarray) -> Tensor:
    """Piecewise-linear interpolation of keys ``(tk [K], vk [K, C])`` at ``t [N]``,
    clamped at the ends: ``[N, C]``."""
    tk_t = torch.as_tensor(np.ascontiguousarray(tk), dtype=t.dtype, device=t.device)
    vk_t = torch.as_tensor(np.ascontiguousarray(vk), dtype=t.dtype, device=t.device)
    if tk_t.numel() == 1:
        return vk_t.expand(t.shape[0], vk_t.shape[1]).clone()
    tc = t.clamp(tk_t[0], tk_t[-1])
    i = torch.searchsorted(tk_t, tc, right=True).clamp(1, tk_t.numel() - 1)
    t0, t1, v0, v1 = tk_t[i - 1], tk_t[i], vk_t[i - 1], vk_t[i]
    w = ((tc - t0) / (t1 - t0).clamp_min(1e-300)).clamp(0, 1)
    return v0 + w[:, None] * (v1 - v0)


#: Motion types and the parameters each accepts.
MOTIONS: tuple[str, ...] = ("static", "linear", "orbit", "bounce", "spin", "keyframe")


def parse_motions(raw: object, where: str, prefix: str) -> list[Motion]:
    """Parse ``motion`` (one mapping or a list of mappings) into :class:`Motion` terms."""
    if raw is None:
        return []
    items = raw if isinstance(raw, list) else [raw]
    out = []
    for j, m in enumerate(items):
        pre = f"{prefix}[{j}]." if isinstance(raw, list) else f"{prefix}."
        kind = get(m, "type", str, where, pre, check=lambda v: v in MOTIONS,
                   expect="one of " + ", ".join(MOTIONS))
        out.append(Motion(kind, _parse_params(kind, m, where, pre)))
    return out


def _parse_params(kind: str, m: Mapping, where: str, pre: str) -> dict:
    num = (float,)
    if kind == "linear":
        return {"to": get_vec(m, "to", 3, where, pre)}
    if kind == "orbit":
        return {"radius": get(m, "radius", num, where, pre, check=lambda v: v >= 0,
                              expect="a radius ≥ 0"),
                "turns": get(m, "turns", num, where, pre, default=1.0),
                "phase_deg": get(m, "phase_deg", num, where, pre, default=0.0)}
    if kind == "bounce":
        return {"height": get(m, "height", num, where, pre),
                "bounces": get(m, "bounces", num, where, pre, default=1.0)}
    if kind == "spin":
        axis = get_vec(m, "axis", 3, where, pre, default=(0.0, 1.0, 0.0))
        if np.linalg.norm(axis) == 0:
            raise InputError(where, f"{pre}axis", "a non-zero vector", axis.tolist())
        return {"axis": axis, "turns": get(m, "turns", num, where, pre, default=1.0),
                "phase_deg": get(m, "phase_deg", num, where, pre, default=0.0)}
    if kind == "keyframe":
        keys = get(m, "keys", list, where, pre, expect="a list of [t, dx, dy, dz(, deg)]")
        try:
            arr = np.asarray(keys, dtype=np.float64)
        except (TypeError, ValueError):
            arr = np.zeros((0, 0))
        if arr.ndim != 2 or arr.shape[0] < 1 or arr.shape[1] not in (4, 5) \
                or np.any(np.diff(arr[:, 0]) <= 0):
            raise InputError(where, f"{pre}keys",
                             "rows [t, dx, dy, dz] or [t, dx, dy, dz, deg] with increasing t",
                             repr(keys)[:60])
        return {"keys": arr, "axis": get_vec(m, "axis", 3, where, pre,
                                             default=(0.0, 1.0, 0.0))}
    return {}
