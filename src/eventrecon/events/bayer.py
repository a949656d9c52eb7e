"""The RGGB Bayer pattern of colour event pixels (and of raw RGB frames).

Channel seen by the pixel at ``(row, col)`` (docs/method.md "Colour and log space"):

======== ============ ============
         even column  odd column
======== ============ ============
even row R (0)        G (1)
odd row  G (1)        B (2)
======== ============ ============

so ``channel = row % 2 + col % 2``. The mask is the one-hot encoding of that channel;
the event losses compare only the channel a pixel sees.
"""

from __future__ import annotations

import torch
from torch import Tensor

from eventrecon.common.errors import InputError

__all__ = ["bayer_channel", "bayer_mask", "bayer_mask_at"]


def bayer_channel(rows: Tensor, cols: Tensor) -> Tensor:
    """Channel index (0 = R, 1 = G, 2 = B) of RGGB pixels.

    Args:
        rows, cols: ``[N]`` (or any broadcastable shapes) integer pixel rows / columns.

    Returns:
        ``[N]`` int64 ``row % 2 + col % 2``, on the inputs' device.

    >>> bayer_channel(torch.tensor([0, 0, 1, 1]), torch.tensor([0, 1, 0, 1]))
    tensor([0, 1, 1, 2])
    """
    if rows.is_floating_point() or cols.is_floating_point():
        raise InputError("bayer_channel", "rows/cols", "integer tensors",
                         f"{rows.dtype}/{cols.dtype}")
    return (torch.remainder(rows, 2) + torch.remainder(cols, 2)).long()


def bayer_mask_at(rows: Tensor, cols: Tensor) -> Tensor:
    """One-hot RGGB channel mask of the given pixels.

    Args:
        rows, cols: ``[N]`` integer pixel rows / columns.

    Returns:
        ``[N, 3]`` float32 one-hot mask on the inputs' device.

    >>> bayer_mask_at(torch.tensor([0, 1]), torch.tensor([1, 1]))
    tensor([[0., 1., 0.],
            [0., 0., 1.]])
    """
    return torch.nn.functional.one_hot(bayer_channel(rows, cols), 3).float()


def bayer_mask(height: int, width: int, device: str | torch.device | None = None) -> Tensor:
    """One-hot RGGB mask of a whole ``height × width`` sensor.

    Returns:
        ``[H, W, 3]`` float32; ``mask[r, c]`` = :func:`bayer_mask_at` ``(r, c)``.

    >>> bayer_mask(2, 2).argmax(-1)
    tensor([[0, 1],
            [1, 2]])
    """
    if height < 1 or width < 1:
        raise InputError("bayer_mask", "height/width", "positive sizes", f"{height}x{width}")
    rows = torch.arange(height, device=device)[:, None].expand(height, width)
    cols = torch.arange(width, device=device)[None, :].expand(height, width)
    return bayer_mask_at(rows, cols)
