"""The camera response model of the rig's RGB frames (supplementary Sec. 8).

A linear CRF with a vertical offset: the pixel value reads ``eps`` below the light
that reaches the sensor, clipped to the valid range,

.. math:: v = \\operatorname{clip}(g \\cdot E - \\varepsilon, 0, 1),

with ``E`` the irradiance integrated over the exposure (∝ light × exposure time) and
``g`` the gain. The fit on the real rig gave ``eps = 3e-2`` (7.65 of 255), which is why
real-data log space is ``L = log(v + 3e-2)``: it equals ``log(g·E)`` where ``v`` is not
clipped. The simulator's ``crf`` effect and ``eventrecon.capture.crf`` calibration both
use this model.
"""

from __future__ import annotations

import numpy as np

__all__ = ["apply_crf", "invert_crf"]


def apply_crf(irradiance: np.ndarray, eps: float, gain: float = 1.0) -> np.ndarray:
    """``clip(gain·irradiance − eps, 0, 1)`` (same shape and float dtype)."""
    return np.clip(gain * irradiance - eps, 0.0, 1.0)


def invert_crf(value: np.ndarray, eps: float, gain: float = 1.0) -> np.ndarray:
    """Irradiance from an unclipped value: ``(value + eps) / gain``."""
    return (value + eps) / gain
