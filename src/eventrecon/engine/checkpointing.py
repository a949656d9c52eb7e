"""Lightning checkpoints written atomically: a crash or SIGKILL never leaves a
half-written checkpoint behind (:func:`eventrecon.common.files.atomic_write_with`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.plugins.io import TorchCheckpointIO

from eventrecon.common.files import atomic_write_with

__all__ = ["AtomicCheckpointIO"]


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning checkpoint I/O that writes through :func:`atomic_write_with`."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: str | Path,
                        storage_options: Any | None = None) -> None:
        atomic_write_with(path, lambda f: torch.save(checkpoint, f))
