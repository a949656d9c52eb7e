"""What the event core is told: its sampling settings and the signal stage's set-up.

Kept apart from :mod:`eventrecon.sim.ideal` (the core) so that the per-pixel path code
(:mod:`eventrecon.sim.paths`) can name these types without importing the core.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["CoreSettings", "SignalSetup", "STEP_TARGET"]

#: The next step aims at this fraction of the sampling bounds.
STEP_TARGET = 0.95


@dataclass
class CoreSettings:
    """Sampling settings (times normalised to ``[0, 1]``).

    Attributes:
        threshold: nominal θ (the step bound is ``β = max_log_step·threshold``).
        max_log_step: fraction of θ a step may change the log signal by.
        max_step, min_step: largest / smallest step.
        max_curvature: slope change per step allowed, in units of ``β``.
        turn_tol: a turn within reach of a level is refined while the path may miss
            more than ``turn_tol·θ/2`` of its extremum.
        block: most samples per pixel evaluated in one iteration.
    """

    threshold: float = 0.5
    max_log_step: float = 0.25
    max_step: float = 2e-3
    min_step: float = 1e-7
    max_curvature: float = 1.0
    turn_tol: float = 1e-3
    block: int = 8


@dataclass
class SignalSetup:
    """What the signal-stage effects configure (arrays over all global pixels).

    Attributes:
        theta_on, theta_off: ``[P_all]`` per-pixel thresholds (frozen part).
        redraw: ``redraw(g [K]) -> (on [K], off [K])`` new thresholds after an event.
        lowpass: ``lowpass(y_a, u_a, u_b, dt) -> y_b`` filter step over ``dt`` (normalised
            time) with input linear from ``u_a`` to ``u_b`` and output ``y_a`` at the start.
        channel_weights: ``[P_all, 3]`` linear weights giving the pixel's intensity.
    """

    theta_on: np.ndarray
    theta_off: np.ndarray
    channel_weights: np.ndarray
    redraw: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
    lowpass: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None
