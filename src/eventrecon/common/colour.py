"""The colour conventions of the data: the gamma of the published frames and the grey
background of the method.

Frames are stored sRGB-like as ``png/255 = I^(1/2.2)`` with ``I`` linear radiance in
[0, 1]; fields render linear radiance, which is encoded the same way before it is saved
or scored. Where no background frame is given, the method composites over a constant
grey of 159/255 in that encoding (the authors' ``bg_color``).

>>> float(abs(srgb_to_linear(np.array([GREY_SRGB], np.uint8))[0] - GREY_LINEAR)) < 1e-7
True
>>> linear_to_srgb(np.array([GREY_LINEAR]))
array([159], dtype=uint8)
"""

from __future__ import annotations

import numpy as np

__all__ = ["GAMMA", "GREY_SRGB", "GREY_LINEAR", "srgb_to_linear", "linear_to_srgb"]

#: The published data encode frames as ``png/255 = linear^(1/2.2)``.
GAMMA: float = 2.2
#: The method's constant background when no background frame is given (8-bit encoded).
GREY_SRGB: int = 159
#: :data:`GREY_SRGB` as linear radiance, ``(159/255)^2.2``.
GREY_LINEAR: float = (GREY_SRGB / 255.0) ** GAMMA


def srgb_to_linear(img_u8: np.ndarray) -> np.ndarray:
    """``(img/255)^2.2`` as float32 (the dataset's gamma)."""
    return (img_u8.astype(np.float32) / 255.0) ** GAMMA


def linear_to_srgb(img: np.ndarray) -> np.ndarray:
    """``round(255·clip(img,0,1)^(1/2.2))`` as uint8 (how renders are saved)."""
    return np.round(255.0 * np.clip(img, 0.0, 1.0) ** (1.0 / GAMMA)).astype(np.uint8)
