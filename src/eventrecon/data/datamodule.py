"""The Lightning DataModule of one segment: the training split, prepared on the right device.

A training "batch" of the method is drawn inside the step from ``(seed, step, rank)``
(:meth:`eventrecon.data.batcher.RayBatcher.sample`), so that a resumed run replays the
same batches and the sampling runs where the data lives (the GPU at paper scale). The
DataModule therefore owns the data, not a sampler: :meth:`SegmentDataModule.setup`
builds the :class:`~eventrecon.data.batcher.RayBatcher` — decayed event prefixes, frames,
background — on the device Lightning assigned to this process (``cuda:k`` for DDP rank
``k``), and the loader only counts steps.
"""

from __future__ import annotations

from collections.abc import Iterator

import lightning as L
import torch

from eventrecon.data.batcher import RayBatcher, Segment
from eventrecon.data.types import SplitData

__all__ = ["SegmentDataModule", "StepCounter"]


class StepCounter(torch.utils.data.IterableDataset):
    """An endless stream of step indices (the batch itself is drawn in the module)."""

    def __iter__(self) -> Iterator[int]:
        i = 0
        while True:
            yield i
            i += 1


class SegmentDataModule(L.LightningDataModule):
    """Training data of one segment.

    Args:
        split: the training split (events, frames, cameras, background).
        segment: the time span trained.
        decay: event decay ``b``.
        bayer: colour (RGGB) event pixels.
        neg_ratio: per view, ``⌊n·(1 − neg_ratio)⌋`` rays on event pixels, the rest
            uniform (:func:`eventrecon.data.sampling.sample_pixels`).

    After :meth:`setup`, :attr:`batcher` holds the split on the trainer's device.
    """

    def __init__(self, split: SplitData, segment: Segment, decay: float, bayer: bool,
                 neg_ratio: float = 0.9) -> None:
        super().__init__()
        self.split, self.segment = split, segment
        self.decay, self.bayer, self.neg_ratio = float(decay), bool(bayer), float(neg_ratio)
        self.batcher: RayBatcher | None = None

    def build(self, device: str | torch.device = "cpu") -> RayBatcher:
        """The :class:`RayBatcher` of this segment on ``device`` (kept in :attr:`batcher`)."""
        device = torch.device(device)
        if self.batcher is None or self.batcher.device != device:
            self.batcher = RayBatcher(self.split, self.segment, self.decay, self.bayer,
                                      self.neg_ratio, device=device)
        return self.batcher

    def setup(self, stage: str) -> None:
        """Build the batcher on this process's device (its own GPU under DDP)."""
        trainer = self.trainer
        self.build(trainer.strategy.root_device if trainer is not None else "cpu")

    def train_dataloader(self) -> torch.utils.data.DataLoader:
        """Step indices only; :meth:`EventNeRFModule.training_step` draws the rays."""
        return torch.utils.data.DataLoader(StepCounter(), batch_size=None)
