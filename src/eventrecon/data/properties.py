"""The physical properties of a scene that training needs, and where each comes from.

Training needs, besides the splits themselves: the log-space guard ``ε``
(``tonemap_eps``), the contrast threshold ``θ``, the event decay ``b``, whether event
pixels are colour (RGGB) pixels, the clip's duration in seconds, its segments and the
clipping cylinder. Each is taken, in this order, from

1. the run's config ``data.<key>`` when it is not null (an explicit choice);
2. the dataset's ``meta.json`` (the simulator and the AEDAT4 converter write one);
3. ``data.fallback.<key>``: what a preset says for datasets that do not record it
   (``data=real``: the published real scenes' ε = 3e-2, b = 0.93, Bayer, five segments;
   ``data=synthetic``: ε = 1e-2, b = 1, one segment) — it never overrides ``meta.json``;
4. nowhere else: a required property found in none of them is an error naming the
   keys, because the synthetic and the real values differ (ε 1e-2 vs 3e-2, b 1 vs
   0.93) and a silent guess trains the wrong method.

``θ`` (0.5) and the cylinder (r = 0.5, y ∈ [−0.75, 0.25]) have defaults shared by both
kinds of data; ``duration_s`` has none (``None``: only ``data.fps`` needs it).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from eventrecon.common.errors import InputError

__all__ = ["SceneProperties", "resolve_properties", "REQUIRED", "DEFAULT_CYLINDER"]

log = logging.getLogger(__name__)

#: Properties that differ between synthetic and real data: no default.
REQUIRED: tuple[str, ...] = ("tonemap_eps", "decay", "bayer")
DEFAULT_CYLINDER: dict[str, float] = {"radius": 0.5, "y_min": -0.75, "y_max": 0.25}
_DEFAULTS: dict[str, Any] = {"threshold": 0.5, "duration_s": None, "segments": None,
                             "cylinder": None, "rgb_fps": None, "scene_name": None}


@dataclass(frozen=True)
class SceneProperties:
    """What the losses, the batcher and the renderer need to know about the data.

    Attributes:
        tonemap_eps: ε of ``L(I) = log(I + ε)`` (> 0).
        threshold: contrast threshold θ (> 0).
        decay: event accumulation decay ``b`` in (0, 1].
        bayer: event pixels are RGGB colour pixels.
        duration_s: seconds the 1000 time units stand for (> 0), or ``None`` if unknown.
        segments: ``[[t0, t1], ...]`` time units, or ``None`` for one segment.
        cylinder: ``{radius, y_min, y_max}`` of the clipping cylinder.
        rgb_fps: the dataset's RGB frame rate, if known.
        scene_name: the scene's name, if known.
    """

    tonemap_eps: float
    threshold: float
    decay: float
    bayer: bool
    duration_s: float | None
    segments: list[list[float]] | None
    cylinder: dict[str, float]
    rgb_fps: float | None = None
    scene_name: str | None = None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def _check(key: str, value: Any, where: str) -> Any:
    """Validate one property; raise :class:`InputError` naming ``where`` and ``key``."""
    if key in ("tonemap_eps", "threshold", "duration_s"):  # None never reaches here
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not value > 0:
            raise InputError(where, key, "a number > 0", value)
        return float(value)
    if key == "decay":
        if not isinstance(value, (int, float)) or isinstance(value, bool) or not 0 < value <= 1:
            raise InputError(where, key, "a decay b in (0, 1]", value)
        return float(value)
    if key == "bayer":
        if not isinstance(value, bool):
            raise InputError(where, key, "true or false", value)
        return value
    if key == "segments" and value is not None:
        ok = isinstance(value, Sequence) and len(value) > 0 and all(
            isinstance(s, Sequence) and len(s) == 2 and float(s[0]) < float(s[1]) for s in value)
        if not ok:
            raise InputError(where, key, "a list of [start, end] time spans with start < end",
                             value)
        return [[float(a), float(b)] for a, b in value]
    if key == "cylinder" and value is not None:
        if not isinstance(value, Mapping) or not set(value) <= set(DEFAULT_CYLINDER):
            raise InputError(where, key, "a mapping with radius, y_min, y_max", value)
        cyl = {**DEFAULT_CYLINDER, **{k: float(v) for k, v in value.items()}}
        if not (cyl["radius"] > 0 and cyl["y_min"] < cyl["y_max"]):
            raise InputError(where, key, "radius > 0 and y_min < y_max", value)
        return cyl
    return value


def resolve_properties(overrides: Mapping[str, Any], meta: Mapping[str, Any],
                       root: Path | str | None = None) -> SceneProperties:
    """Merge config ``overrides`` (``data.*``, null = unset) over the dataset's ``meta``.

    Args:
        overrides: the run's ``data`` config (the property keys and ``fallback``).
        meta: the dataset's ``meta.json`` contents (``{}`` without one).
        root: the dataset folder, for error messages.

    Raises:
        InputError: a required property is in neither (the message names the keys and
            the ``data=real`` / ``data=synthetic`` presets), or a value is out of range.

    >>> p = resolve_properties({"decay": 0.5, "fallback": {"tonemap_eps": 0.03, "bayer": True}},
    ...                        {"tonemap_eps": 0.01, "decay": 1.0})
    >>> p.decay, p.tonemap_eps, p.bayer, p.threshold
    (0.5, 0.01, True, 0.5)
    """
    meta_file = f"{root}/meta.json" if root is not None else "meta.json"
    fallback = overrides.get("fallback") or {}
    values: dict[str, Any] = {}
    missing = []
    for key in (*REQUIRED, *_DEFAULTS):
        if overrides.get(key) is not None:
            values[key] = _check(key, overrides[key], f"config data.{key}")
        elif meta.get(key) is not None:
            values[key] = _check(key, meta[key], meta_file)
        elif fallback.get(key) is not None:
            values[key] = _check(key, fallback[key], f"config data.fallback.{key}")
        elif key in REQUIRED:
            missing.append(key)
        else:
            values[key] = _DEFAULTS[key]
    if missing:
        keys = ", ".join(f"data.{k}" for k in missing)
        raise InputError(meta_file, ", ".join(missing),
                         f"the scene's properties: the dataset has no meta.json, so set "
                         f"{keys} or choose data=real (published real scenes: eps 3e-2, "
                         f"decay 0.93, Bayer, 5 segments) or data=synthetic", "missing")
    values["cylinder"] = values["cylinder"] or dict(DEFAULT_CYLINDER)
    if values["rgb_fps"] is not None:
        values["rgb_fps"] = float(values["rgb_fps"])
    return SceneProperties(**values)
