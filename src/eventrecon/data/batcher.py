"""Training rays of one segment: the per-iteration batch of the method.

Each call of :meth:`RayBatcher.sample` draws, with its own generator,

1. a window ``(t0, t1)`` of the segment (normalised times, docs/method.md "Per-iteration
   sampling"), shared by all views;
2. ``n_rays`` pixels split equally over the training views, per view
   ``⌊n·(1 − neg_ratio)⌋`` on pixels with ``E(t0, t1) ≠ 0`` and the rest uniform over
   the image, each set without replacement (the authors' ``random_sample``);
3. per view, a reference frame among the two nearest to ``t1`` (drawn for each view
   on its own, as the authors' code does) and ``E_ref→1 = V(t1) − V(t_ref)``;
4. the pixel positions jittered by ±0.5 px (the renderer casts the rays through them).

All tensors live on the batcher's device; the generator makes the batch a pure
function of ``(seed, step)``, so a resumed run sees the same batches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from eventrecon.common.colour import GREY_LINEAR, srgb_to_linear
from eventrecon.data import sampling
from eventrecon.data.types import SplitData
from eventrecon.events.accumulate import DecayedEvents
from eventrecon.events.bayer import bayer_mask_at
from eventrecon.render.cameras import Cameras

__all__ = ["RayBatcher", "Segment", "background_linear"]


@dataclass(frozen=True)
class Segment:
    """A time span ``[start, end]`` in time units; fields see ``(t − start) / (end − start)``."""

    start: float
    end: float

    def normalise(self, t: Tensor | np.ndarray | float) -> Tensor | np.ndarray | float:
        return (t - self.start) / (self.end - self.start)

    def units(self, t_norm: Tensor | float) -> Tensor | float:
        return self.start + t_norm * (self.end - self.start)


def background_linear(split: SplitData) -> Tensor:
    """``[V, H, W, 3]`` linear background: the split's frames, else the method's constant
    grey (:data:`eventrecon.common.colour.GREY_LINEAR`)."""
    cams = split.cameras
    if split.background is not None:
        return torch.from_numpy(srgb_to_linear(split.background))
    return torch.full((len(cams), cams.height, cams.width, 3), GREY_LINEAR)


class RayBatcher:
    """Samples the training batch of one segment (see module docstring).

    Args:
        split: the training split (events, frames, cameras, background).
        segment: the time span trained.
        decay: event decay ``b`` (1 = plain polarity sum).
        bayer: whether event pixels are colour (RGGB) pixels.
        neg_ratio: per view, ``⌊n·(1 − neg_ratio)⌋`` of its ``n`` rays go to pixels with
            events and the rest uniformly over all pixels, each set without replacement.
        device: where the batch tensors live.
    """

    def __init__(self, split: SplitData, segment: Segment, decay: float, bayer: bool,
                 neg_ratio: float = 0.9, device: str | torch.device = "cpu") -> None:
        if split.events is None:
            raise ValueError(f"{split.root}: events: the training split has no events/")
        self.cameras: Cameras = split.cameras
        self.segment = segment
        self.neg_ratio = neg_ratio
        self.bayer = bayer
        self.device = torch.device(device)
        H, W = self.cameras.height, self.cameras.width
        self.events = DecayedEvents.from_streams(split.events, H, W, decay, device=self.device)
        frame_times = np.asarray(split.frame_times, dtype=np.float64)
        # Frames in (or nearest to) the segment serve as references.
        inside = (frame_times >= segment.start) & (frame_times <= segment.end)
        if not inside.any():
            inside[np.argmin(np.abs(frame_times - 0.5 * (segment.start + segment.end)))] = True
        idx = np.flatnonzero(inside)
        self.frame_times = torch.from_numpy(frame_times[idx]).to(self.device)  # time units
        self.frames = torch.from_numpy(srgb_to_linear(split.frames[idx])).to(self.device)
        self.background = background_linear(split).to(self.device)
        self.loss_mask = (None if split.loss_mask is None
                          else torch.from_numpy(split.loss_mask).to(self.device))
        #: ``(t0, t1)`` normalised window of the last :meth:`sample` (Python floats).
        self.last_window: tuple[float, float] = (0.0, 1.0)

    @property
    def n_views(self) -> int:
        return len(self.cameras)

    def sample(self, n_rays: int, gen: torch.Generator) -> dict[str, Tensor]:
        """One training batch of ``N = n_rays`` rays.

        Returns:
            dict with ``view, row, col [N]``, ``uv [N, 2]`` the jittered pixel positions
            (float64, column and row), ``t0, t1, t_ref [N,1]`` (normalised),
            ``events [N]`` = E(t0,t1), ``events_ref [N]`` = V(t1) − V(t_ref),
            ``ref_rgb [N,3]`` (or ``[N]`` raw), ``bg [N,3]``, ``mask [N,3]`` (Bayer
            one-hot) or ``None`` for grey event pixels, ``weight [N]`` the split's loss
            mask at each ray's pixel or ``None`` (none given).
        """
        seg, H, W = self.segment, self.cameras.height, self.cameras.width
        t0, t1 = sampling.sample_window(gen)
        self.last_window = (t0, t1)
        t0u, t1u = float(seg.units(t0)), float(seg.units(t1))
        counts = sampling.rays_per_view(n_rays, self.n_views, gen)
        event_map = self.events.window_all(t0u, t1u) != 0  # [V, H, W]
        view, row, col = sampling.sample_pixels(event_map, counts, self.neg_ratio, gen)
        pix = (view * H + row) * W + col
        n = pix.shape[0]
        ref = sampling.pick_reference(self.frame_times, t1u, gen, self.n_views)[view]  # [N]
        t_ref_u = self.frame_times[ref].to(torch.float64)
        # V at t1, t0 and t_ref in one query: E(t0, t1) = V(t1) − V(t0) and
        # E_ref→1 = V(t1) − V(t_ref), as DecayedEvents.window subtracts them
        ends = torch.tensor([t1u, t0u], dtype=torch.float64, device=self.device)
        v1, v0, v_ref = self.events.value(
            pix.repeat(3), torch.cat([ends.repeat_interleave(n), t_ref_u])).split(n)
        events, events_ref = v1 - v0, v1 - v_ref
        uv = torch.stack([col, row], -1).double()
        uv = sampling.jitter(uv, gen)
        # Colour event pixels see one channel; grey event pixels see the channel mean
        # (mask None, see eventrecon.engine.losses.event_channels).
        mask = bayer_mask_at(row, col).float() if self.bayer else None
        return {
            "view": view, "row": row, "col": col, "uv": uv,
            "t0": torch.full((n, 1), float(t0), device=self.device),
            "t1": torch.full((n, 1), float(t1), device=self.device),
            "t_ref": seg.normalise(t_ref_u)[:, None].to(self.device, torch.float32),
            "events": events.float(), "events_ref": events_ref.float(),
            "ref_rgb": self.frames[ref, view, row, col],
            "bg": self.background[view, row, col],
            "mask": mask,
            "weight": None if self.loss_mask is None else self.loss_mask[view, row, col],
        }
