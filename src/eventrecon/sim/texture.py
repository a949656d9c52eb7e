"""Albedo textures evaluated at object-local surface points.

Textures live in object-local coordinates, so they move and spin with their object and
produce events as they pass the pixels.

- ``solid``: ``color [3]``;
- ``checker``: ``colors [[3], [3]]``, ``size`` (cell edge): colour index
  ``Σ_i ⌊p_i/size + o⌋ mod 2``;
- ``stripes``: ``colors``, ``period``, ``axis [3]``: index ``⌊(p·â)/(period/2) + o⌋ mod 2``.

The lattice offset ``o = 0.31`` keeps cell borders off the planes ``p_i = k·size/2``
on which box faces usually lie (a border on a face would make its colour depend on
rounding).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from eventrecon.common.errors import InputError
from eventrecon.sim.config import get, get_vec

__all__ = ["Texture", "TextureTable", "parse_texture", "TEXTURES"]

TEXTURES: tuple[str, ...] = ("solid", "checker", "stripes")
_OFFSET = 0.31


@dataclass
class Texture:
    """``albedo(p [N, 3]) -> [N, 3]`` linear reflectance in ``[0, 1]``."""

    kind: str
    colors: np.ndarray  # [2, 3] (solid: both rows equal)
    size: float = 1.0
    axis: np.ndarray | None = None

    def albedo(self, p: Tensor) -> Tensor:
        """Albedo at object-local points ``p [N, 3]`` (float64) -> ``[N, 3]``."""
        cols = torch.as_tensor(self.colors, dtype=p.dtype, device=p.device)
        if self.kind == "solid":
            return cols[0].expand(p.shape[0], 3)
        if self.kind == "checker":
            idx = torch.floor(p / self.size + _OFFSET) @ torch.ones(3, dtype=p.dtype,
                                                                    device=p.device)
        else:
            a = torch.as_tensor(self.axis, dtype=p.dtype, device=p.device)
            idx = torch.floor(p @ (a / a.norm()) / (0.5 * self.size) + _OFFSET)
        return cols[torch.remainder(idx, 2).long()]


class TextureTable:
    """Several textures evaluated in one pass: ``albedo(k [N], p [N, 3])`` gives texture
    ``k[i]``'s albedo at ``p[i]``, the same formulas as :meth:`Texture.albedo`.

    >>> tt = TextureTable([Texture("solid", np.full((2, 3), 0.5)),
    ...                    Texture("stripes", np.eye(3)[:2], 0.2, np.array([1., 0, 0]))])
    >>> tt.albedo(torch.tensor([0, 1, 1]), torch.tensor([[0., 0, 0], [0., 0, 0], [.1, 0, 0]],
    ...                                                  dtype=torch.float64)).tolist()
    [[0.5, 0.5, 0.5], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    """

    def __init__(self, textures: list[Texture]):
        self.kind = torch.tensor([TEXTURES.index(t.kind) for t in textures])
        self.colors = torch.as_tensor(np.stack([t.colors for t in textures]), dtype=torch.float64)
        self.size = torch.tensor([float(t.size) for t in textures], dtype=torch.float64)
        axes = np.stack([np.zeros(3) if t.axis is None else t.axis for t in textures])
        norm = np.linalg.norm(axes, axis=1, keepdims=True)
        self.axis = torch.as_tensor(axes / np.where(norm > 0, norm, 1.0), dtype=torch.float64)

    def albedo(self, k: Tensor, p: Tensor) -> Tensor:
        """``[N, 3]`` albedo of textures ``k [N]`` (long) at local points ``p [N, 3]``."""
        size = self.size[k]
        ones = torch.ones(3, dtype=p.dtype, device=p.device)
        checker = torch.floor(p / size[:, None] + _OFFSET) @ ones
        stripes = torch.floor(((p * self.axis[k]) @ ones) / (0.5 * size) + _OFFSET)
        kind = self.kind[k]
        idx = torch.where(kind == 1, checker, torch.where(kind == 2, stripes,
                                                          torch.zeros_like(stripes)))
        return self.colors[k, torch.remainder(idx, 2).long()]


def parse_texture(raw: Mapping | None, where: str, prefix: str) -> Texture:
    """Parse a ``texture`` mapping (``type`` one of :data:`TEXTURES`)."""
    if raw is None:
        return Texture("solid", np.full((2, 3), 0.7))
    kind = get(raw, "type", str, where, prefix, check=lambda v: v in TEXTURES,
               expect="one of " + ", ".join(TEXTURES))
    if kind == "solid":
        c = get_vec(raw, "color", 3, where, prefix)
        cols = np.stack([c, c])
    else:
        pair = get(raw, "colors", list, where, prefix, expect="two RGB triples")
        if len(pair) != 2:
            raise InputError(where, f"{prefix}colors", "two RGB triples", repr(pair))
        cols = np.stack([get_vec({"c": c}, "c", 3, where, f"{prefix}colors[{i}].")
                         for i, c in enumerate(pair)])
    if np.any(cols < 0) or np.any(cols > 1):
        raise InputError(where, f"{prefix}color(s)", "linear reflectance in [0, 1]",
                         cols.tolist())
    size = get(raw, "size" if kind == "checker" else "period", float, where, prefix,
               default=0.1, check=lambda v: v > 0, expect="a length > 0")
    axis = get_vec(raw, "axis", 3, where, prefix, default=(0.0, 1.0, 0.0)) \
        if kind == "stripes" else None
    return Texture(kind, cols, size, axis)
