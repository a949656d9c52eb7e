"""Collapsed runs: a field that renders the empty scene is not a result.

A run *collapses* when its density dies out and every render shows the background: the
losses then sit at the value of an empty field, and on a scene that is mostly
background the held-out PSNR can look respectable while nothing was reconstructed. Two
signs, either one enough (:func:`collapse_reason`):

- the mean rendered opacity of the training renders (fine level, the three render
  times; logged every ``trainer.log_every`` steps) stays below ``opacity_floor`` over
  the last ``window`` share of the logged steps of some segment;
- the held-out PSNR is within ``psnr_margin`` dB of the empty field's on the same frames
  (``psnr_background``), and so is the PSNR on the subject's region where the run has
  one (``psnr_subject`` against ``psnr_background_subject``): a run can trade a better
  subject for a worse background and land on the empty field's full-frame PSNR by chance
  (`rig_drift` full, seed 0: 0.004 dB from it with the subject +1.21 dB better).

A collapsed run is written with ``status: collapsed`` and its reason; the tables and the
accuracy-vs-time figure show "collapsed" instead of its numbers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from eventrecon.common.errors import InputError

__all__ = ["CollapseRule", "opacity_collapsed", "collapse_reason"]


@dataclass(frozen=True)
class CollapseRule:
    """Thresholds of :func:`collapse_reason` (``trainer.collapse`` in the config)."""

    opacity_floor: float = 1e-3
    """Mean opacity below which a render is (nearly) the background."""
    window: float = 0.25
    """Share of the logged steps, at the end of a segment, that must all be below the floor."""
    psnr_margin: float = 0.05
    """A held-out PSNR within this many dB of the empty field's is a collapse."""

    def __post_init__(self) -> None:
        if not (self.opacity_floor >= 0 and 0 < self.window <= 1 and self.psnr_margin >= 0):
            raise InputError("config", "trainer.collapse",
                             "opacity_floor >= 0, 0 < window <= 1, psnr_margin >= 0", self)


def opacity_collapsed(log: Sequence[tuple[int, float]], rule: CollapseRule) -> bool:
    """Whether the last ``ceil(window · n)`` of the ``n`` logged ``(step, opacity)`` points
    are all below the floor (no points: not collapsed).

    >>> rule = CollapseRule(opacity_floor=1e-3, window=0.5)
    >>> opacity_collapsed([(1, 0.2), (2, 0.1), (3, 1e-4), (4, 1e-5)], rule)
    True
    >>> opacity_collapsed([(1, 0.2), (2, 1e-4), (3, 1e-4), (4, 0.3)], rule)
    False
    """
    if not log:
        return False
    k = max(1, math.ceil(rule.window * len(log)))
    return all(o < rule.opacity_floor for _, o in list(log)[-k:])


def _near(a: float | None, b: float | None, margin: float) -> bool | None:
    """Whether two finite PSNRs lie within ``margin``; ``None`` when either is missing."""
    if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)):
        return None
    return abs(a - b) <= margin


def collapse_reason(opacity_logs: Sequence[Sequence[tuple[int, float]]], psnr: float | None,
                    psnr_background: float | None, rule: CollapseRule,
                    psnr_subject: float | None = None,
                    psnr_background_subject: float | None = None) -> str | None:
    """Why a run counts as collapsed, or ``None``.

    Args:
        opacity_logs: per segment, the logged ``(step, mean opacity)`` of training.
        psnr, psnr_background: held-out PSNR of the run and of the empty field (or None).
        rule: the thresholds.
        psnr_subject, psnr_background_subject: the same on the subject's region (or None:
            the full frame decides alone).

    >>> collapse_reason([[(25, 0.0), (50, 0.0)]], 21.3, 21.3, CollapseRule())
    'segment 0: mean opacity below 0.001 over the last 25% of training'
    >>> collapse_reason([[(25, 0.2)]], 21.32, 21.30, CollapseRule())
    'held-out PSNR 21.32 dB within 0.05 dB of the empty field (21.30 dB)'
    >>> collapse_reason([[(25, 0.2)]], 24.0, 21.3, CollapseRule()) is None
    True
    >>> collapse_reason([[(25, 0.2)]], 22.07, 22.06, CollapseRule(), 16.88, 15.67) is None
    True
    """
    for k, log in enumerate(opacity_logs):
        if opacity_collapsed(log, rule):
            return (f"segment {k}: mean opacity below {rule.opacity_floor:g} over the last "
                    f"{rule.window:.0%} of training")
    subject_near = _near(psnr_subject, psnr_background_subject, rule.psnr_margin)
    if _near(psnr, psnr_background, rule.psnr_margin) and subject_near is not False:
        return (f"held-out PSNR {psnr:.2f} dB within {rule.psnr_margin:g} dB of the empty "
                f"field ({psnr_background:.2f} dB)")
    return None
