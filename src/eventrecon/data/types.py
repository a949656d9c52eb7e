"""In-memory structures of a dataset in the published layout.

Events are :class:`~eventrecon.events.stream.EventStream` arrays; frames are uint8,
encoded as stored (linearise with :func:`eventrecon.common.colour.srgb_to_linear`). The
event and colour names are re-exported here for readers of a dataset.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eventrecon.common.colour import GAMMA, linear_to_srgb, srgb_to_linear
from eventrecon.events.stream import EventStream
from eventrecon.render.cameras import Cameras

__all__ = ["EventStream", "SplitData", "Dataset", "srgb_to_linear", "linear_to_srgb", "GAMMA"]


@dataclass
class SplitData:
    """One split (``train`` or ``validation``) of a scene.

    Attributes:
        root: the split folder.
        cameras: the split's ``V`` cameras (view order = sorted file order).
        events: one :class:`EventStream` per view, or ``None`` if the split has none.
        frame_times: ``[F]`` float64 time units of the RGB frames (folder names).
        frames: ``[F, V, H, W, 3]`` uint8 (or ``[F, V, H, W]`` single-channel Bayer raw).
        background: ``[V, H, W, 3]`` uint8 empty-scene frame per view, or ``None``.
        masks: ``[F, V, H, W]`` bool foreground masks, or ``None``.
        loss_mask: ``[V, H, W]`` float32 in ``[0, 1]``: a static ``mask/<view>.png`` (its
            first channel / 255), by which the authors weight the photometric losses of
            training rays (:mod:`eventrecon.engine.losses`); ``None`` without one (per-frame
            ``mask/<time>/`` folders, the simulator's, are never training masks).
    """

    root: Path
    cameras: Cameras
    events: list[EventStream] | None
    frame_times: np.ndarray
    frames: np.ndarray
    background: np.ndarray | None = None
    masks: np.ndarray | None = None
    loss_mask: np.ndarray | None = None

    @property
    def n_views(self) -> int:
        return len(self.cameras)


@dataclass
class Dataset:
    """A scene: its splits plus the metadata the simulator or converter recorded.

    ``meta`` keys used by training (all optional, with the defaults of docs/method.md):
    ``tonemap_eps`` (1e-2 synthetic, 3e-2 real), ``threshold`` (0.5), ``decay`` (1.0
    synthetic, 0.93 real), ``bayer`` (bool: colour event pixels), ``duration_s``,
    ``cylinder`` ({radius, y_min, y_max}), ``segments`` (list of [t0, t1] time units),
    ``scene`` (the full scene config), ``effects``.
    """

    root: Path
    splits: dict[str, SplitData] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)
