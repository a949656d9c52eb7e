"""In-memory structures of a dataset in the published layout.

Compact dtypes: event x, y int16, t float64 (time units in [0, 1000]), p int8 (±1);
frames uint8 sRGB-encoded as stored (linearise with :func:`srgb_to_linear`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from eventrecon.render.cameras import Cameras

__all__ = ["EventStream", "SplitData", "Dataset", "srgb_to_linear", "linear_to_srgb", "GAMMA"]

#: The published data encode frames as ``png/255 = linear^(1/2.2)``.
GAMMA: float = 2.2


def srgb_to_linear(img_u8: np.ndarray) -> np.ndarray:
    """``(img/255)^2.2`` as float32 (the dataset's gamma, method.md)."""
    return (img_u8.astype(np.float32) / 255.0) ** GAMMA


def linear_to_srgb(img: np.ndarray) -> np.ndarray:
    """``round(255·clip(img,0,1)^(1/2.2))`` as uint8 (how renders are saved)."""
    return np.round(255.0 * np.clip(img, 0.0, 1.0) ** (1.0 / GAMMA)).astype(np.uint8)


@dataclass
class EventStream:
    """The events of one view, sorted by time.

    Attributes:
        x, y: ``[N]`` int16 pixel column / row.
        t: ``[N]`` float64 time units in [0, 1000], non-decreasing.
        p: ``[N]`` int8 polarity in {−1, +1}.
    """

    x: np.ndarray
    y: np.ndarray
    t: np.ndarray
    p: np.ndarray

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @staticmethod
    def empty() -> EventStream:
        return EventStream(np.zeros(0, np.int16), np.zeros(0, np.int16),
                           np.zeros(0, np.float64), np.zeros(0, np.int8))


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
    """

    root: Path
    cameras: Cameras
    events: list[EventStream] | None
    frame_times: np.ndarray
    frames: np.ndarray
    background: np.ndarray | None = None
    masks: np.ndarray | None = None

    @property
    def n_views(self) -> int:
        return len(self.cameras)


@dataclass
class Dataset:
    """A scene: its splits plus the metadata the simulator or converter recorded.

    ``meta`` keys used by training (all optional, with the defaults of method.md):
    ``tonemap_eps`` (1e-2 synthetic, 3e-2 real), ``threshold`` (0.5), ``decay`` (1.0
    synthetic, 0.93 real), ``bayer`` (bool: colour event pixels), ``duration_s``,
    ``cylinder`` ({radius, y_min, y_max}), ``segments`` (list of [t0, t1] time units),
    ``scene`` (the full scene config), ``effects``.
    """

    root: Path
    splits: dict[str, SplitData] = field(default_factory=dict)
    meta: dict = field(default_factory=dict)
