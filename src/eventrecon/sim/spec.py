"""The scene-level settings of a simulation, parsed and validated from the scene config.

Fields (defaults in brackets; time units ``u`` span ``[0, 1000]``):

- ``name``, ``seed`` [0]; ``width`` [96], ``height`` [72] (DAVIS: 346×260);
- ``duration_s`` [2.0] seconds the 1000 time units stand for; ``rgb_fps`` [5] training
  frames; ``eval_fps`` [5] ground-truth times of the held-out views;
- ``tonemap_eps`` [1e-2], ``threshold`` [0.5], ``decay`` [1.0] (recorded for training),
  ``cylinder`` [{radius 0.5, y_min −0.75, y_max 0.25}], ``segments`` [[[0, 1000]]];
- sampling: ``max_log_step`` [0.25] (fraction of θ), ``max_step`` [2.0 u],
  ``min_step`` [1e-3 u], ``supersample`` [1] rays per pixel side of the event signal;
  ``frame_supersample`` [= supersample] rays per pixel side of the RGB frames,
  backgrounds, masks and ground-truth renders (an area-averaged pixel, as a camera's:
  a pixel-centre ground truth aliases at texture and silhouette edges, which no model
  trained on jittered rays can reproduce);
- ``background_exposures`` [32] exposures averaged into each view's empty-scene plate
  (``background/``), as a plate is captured: the frame effects run on every exposure and
  the 8-bit frames are averaged, so a noise effect's spread shrinks by √N while vignetting,
  the CRF offset and blur stay (1 = a single frame, as noisy as a training frame);
- ``rig``: ``n_train`` [6], ``n_heldout`` [1], ``radius`` [2.5], ``elevation_deg`` [15],
  ``fov_deg`` [32], ``target`` [[0, −0.25, 0]], ``dist`` [zeros], ``heldout_azimuth_deg``
  [180 / n_train: half-way between training cameras 0 and 1; the held-out ring is
  rotated by it], or ``camdict: PATH`` (the last ``n_heldout`` views of the file are
  held out);
- ``objects``, ``light``, ``background`` (:mod:`eventrecon.sim.scene`);
- ``events``, ``frames``: ordered effect lists (:mod:`eventrecon.sim.event_effects`,
  :mod:`eventrecon.sim.frame_effects`).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from eventrecon import TIME_SPAN
from eventrecon.common.errors import InputError
from eventrecon.render.cameras import Cameras, load_camdict, ring_rig
from eventrecon.sim.config import get, get_vec, positive, to_plain
from eventrecon.sim.event_effects import EVENT_EFFECTS
from eventrecon.sim.frame_effects import FRAME_EFFECTS
from eventrecon.sim.registry import Effect
from eventrecon.sim.scene import Scene, parse_scene

__all__ = ["SceneSpec", "parse_spec", "frame_times", "build_cameras"]

log = logging.getLogger(__name__)


@dataclass
class SceneSpec:
    """Everything the simulator needs, validated (see the module docstring)."""

    name: str
    seed: int
    width: int
    height: int
    duration_s: float
    rgb_fps: float
    eval_fps: float
    tonemap_eps: float
    threshold: float
    decay: float
    cylinder: dict
    segments: list
    max_log_step: float
    max_step: float
    min_step: float
    supersample: int
    frame_supersample: int
    background_exposures: int
    rig: dict
    scene: Scene
    event_effects: list[Effect] = field(default_factory=list)
    frame_effects: list[Effect] = field(default_factory=list)
    raw: dict = field(default_factory=dict)
    where: str = "scene"

    @property
    def bayer(self) -> bool:
        """Colour event pixels (the ``bayer`` event effect is listed)."""
        return any(e.name == "bayer" for e in self.event_effects)


def parse_spec(cfg: object, where: str | None = None) -> SceneSpec:
    """Validate a scene config (``DictConfig`` or ``dict``) into a :class:`SceneSpec`."""
    raw = to_plain(cfg)
    if not isinstance(raw, Mapping):
        raise InputError(where or "scene", "<root>", "a mapping of scene fields",
                         type(raw).__name__)
    name = get(raw, "name", str, where or "scene")
    w = where or f"scene {name}"
    cyl_raw = get(raw, "cylinder", Mapping, w, default={})
    cyl = {"radius": get(cyl_raw, "radius", float, w, "cylinder.", 0.5, positive),
           "y_min": get(cyl_raw, "y_min", float, w, "cylinder.", -0.75),
           "y_max": get(cyl_raw, "y_max", float, w, "cylinder.", 0.25)}
    if cyl["y_min"] >= cyl["y_max"]:
        raise InputError(w, "cylinder.y_min", "< cylinder.y_max", cyl["y_min"])
    segs = get(raw, "segments", list, w, default=[[0.0, TIME_SPAN]])
    for i, s in enumerate(segs):
        if not (isinstance(s, (list, tuple)) and len(s) == 2 and 0 <= s[0] < s[1] <= TIME_SPAN):
            raise InputError(w, f"segments[{i}]", f"[t0, t1] with 0 ≤ t0 < t1 ≤ {TIME_SPAN:g}",
                             s)
    rig = get(raw, "rig", Mapping, w, default={})
    spec = SceneSpec(
        name=name,
        seed=get(raw, "seed", int, w, default=0),
        width=get(raw, "width", int, w, default=96, check=positive),
        height=get(raw, "height", int, w, default=72, check=positive),
        duration_s=get(raw, "duration_s", float, w, default=2.0, check=positive),
        rgb_fps=get(raw, "rgb_fps", float, w, default=5.0, check=positive),
        eval_fps=get(raw, "eval_fps", float, w, default=5.0, check=positive),
        tonemap_eps=get(raw, "tonemap_eps", float, w, default=1e-2, check=positive),
        threshold=get(raw, "threshold", float, w, default=0.5, check=positive,
                      expect="a contrast threshold > 0"),
        decay=get(raw, "decay", float, w, default=1.0, check=lambda v: 0 < v <= 1,
                  expect="a decay in (0, 1]"),
        cylinder=cyl, segments=[[float(a), float(b)] for a, b in segs],
        max_log_step=get(raw, "max_log_step", float, w, default=0.25,
                         check=lambda v: 0 < v <= 1, expect="a fraction of θ in (0, 1]"),
        max_step=get(raw, "max_step", float, w, default=2.0, check=positive) / TIME_SPAN,
        min_step=get(raw, "min_step", float, w, default=1e-3, check=positive) / TIME_SPAN,
        supersample=get(raw, "supersample", int, w, default=1, check=positive),
        frame_supersample=get(raw, "frame_supersample", int, w,
                              default=get(raw, "supersample", int, w, default=1, check=positive),
                              check=positive),
        background_exposures=get(raw, "background_exposures", int, w, default=32,
                                 check=positive, expect="a number of exposures ≥ 1"),
        rig=dict(rig), scene=parse_scene(raw, w),
        event_effects=EVENT_EFFECTS.build(raw.get("events"), w),
        frame_effects=FRAME_EFFECTS.build(raw.get("frames"), w),
        raw=dict(raw), where=w)
    if spec.min_step > spec.max_step:
        raise InputError(w, "min_step", "≤ max_step", spec.min_step * TIME_SPAN)
    out = spec.scene.cylinder_violation(**cyl)
    if out > 1e-9:
        log.warning("%s: an object's bounding sphere leaves the clipping cylinder by %.3f; "
                    "training with clipping cannot represent that part", w, out)
    return spec


def frame_times(duration_s: float, fps: float, where: str = "scene",
                field_name: str = "rgb_fps") -> np.ndarray:
    """``[F]`` time units ``round(k·1000/(fps·duration_s))``, ``k = 0, 1, …`` up to 1000.

    Rounded to whole units because frame folders are named by them: the frame stored
    under ``rgb/0333/`` is rendered at exactly ``t = 333``.

    >>> frame_times(2.0, 5.0).tolist()
    [0.0, 100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0, 900.0, 1000.0]
    >>> frame_times(1.0, 3.0).tolist()
    [0.0, 333.0, 667.0, 1000.0]
    """
    step = TIME_SPAN / (fps * duration_s)
    if step < 1.0:
        raise InputError(where, field_name, f"≤ {TIME_SPAN / duration_s:g} frames per second "
                         "(frame folders are named by whole time units)", fps)
    n = int(np.floor(TIME_SPAN / step + 1e-9))
    return np.round(np.arange(n + 1) * step)


def build_cameras(spec: SceneSpec) -> tuple[Cameras, Cameras]:
    """``(train, heldout)`` cameras: a ring rig, or the views of ``rig.camdict``."""
    r, w = spec.rig, spec.where
    n_held = get(r, "n_heldout", int, w, "rig.", 1, lambda v: v >= 0)
    if r.get("camdict"):
        cams = load_camdict(r["camdict"])
        if (cams.width, cams.height) != (spec.width, spec.height):
            raise InputError(w, "width/height",
                             f"the image size of rig.camdict {r['camdict']} "
                             f"({cams.width}×{cams.height}: set width={cams.width} "
                             f"height={cams.height})", f"{spec.width}×{spec.height}")
        if n_held >= len(cams):
            raise InputError(w, "rig.n_heldout", f"< the {len(cams)} views of the camdict", n_held)
        n_tr = len(cams) - n_held
        return cams.select(range(n_tr)), cams.select(range(n_tr, len(cams)))
    n_tr = get(r, "n_train", int, w, "rig.", 6, positive)
    kw = dict(radius=get(r, "radius", float, w, "rig.", 2.5, positive),
              elevation_deg=get(r, "elevation_deg", float, w, "rig.", 15.0),
              fov_deg=get(r, "fov_deg", float, w, "rig.", 32.0, lambda v: 0 < v < 180),
              target=tuple(get_vec(r, "target", 3, w, "rig.", (0.0, -0.25, 0.0))),
              dist=tuple(get_vec(r, "dist", 5, w, "rig.", (0.0,) * 5)))
    train = ring_rig(n_tr, spec.width, spec.height, **kw)
    held_az = get(r, "heldout_azimuth_deg", float, w, "rig.", 180.0 / n_tr)
    held = ring_rig(max(n_held, 1), spec.width, spec.height,
                    azimuth_offset_deg=held_az, names=[f"{n_tr + i:02d}"
                                                           for i in range(max(n_held, 1))], **kw)
    return train, held.select(range(n_held))
