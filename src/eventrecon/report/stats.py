"""Means over seeds with 95 % intervals, and paired differences between settings.

A table cell is the mean over the seeds that were scored, with the half-width of the
two-sided 95 % Student-t interval of that mean,

.. math:: \\bar x \\pm t_{0.975,\\,n-1}\\, s / \\sqrt{n},

(no interval for ``n = 1``). A difference between two settings is *paired*: it is taken
per (scene, seed) — the two runs share the data and the seed — and the interval is the
one of the mean paired difference, so the spread of the scenes does not hide an effect
that every scene shows.

>>> m = mean_ci([23.0, 24.0, 25.0])
>>> round(m.mean, 3), round(m.half, 3), m.n
(24.0, 2.484, 3)
>>> m.excludes_zero
True
>>> mean_ci([1.0]).half is None
True

How many values an interval needs: at the spread ``s`` of ``m``, the 95 % interval's
half-width falls below ``|e|`` once :math:`t_{0.975,\\,n-1}\\, s/\\sqrt n < |e|`
(:func:`pairs_to_resolve`) -- with ``e`` an effect someone else measured, that is the
number of (scene, seed) pairs it would take to see that effect here.

>>> pairs_to_resolve(m, 1.0)      # s = 1: t_{n-1}/sqrt(n) < 1 from n = 7 on
7
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = ["MeanCI", "mean_ci", "t_quantile", "pairs_to_resolve"]


def t_quantile(dof: int, p: float = 0.975) -> float:
    """The ``p`` quantile of Student's t with ``dof`` degrees of freedom.

    >>> round(t_quantile(2), 3), round(t_quantile(1000), 2)
    (4.303, 1.96)
    """
    from scipy.stats import t

    return float(t.ppf(p, dof))


@dataclass(frozen=True)
class MeanCI:
    """A mean, the half-width of its 95 % interval (``None`` for one value), and ``n``."""

    mean: float
    half: float | None
    n: int

    @property
    def low(self) -> float:
        return self.mean - (self.half or 0.0)

    @property
    def high(self) -> float:
        return self.mean + (self.half or 0.0)

    @property
    def excludes_zero(self) -> bool:
        """Whether the interval lies strictly on one side of 0 (``False`` for ``n = 1``)."""
        return self.half is not None and (self.low > 0 or self.high < 0)


def mean_ci(values: Sequence[float]) -> MeanCI:
    """Mean and 95 % Student-t half-width of ``values`` (module docstring)."""
    vals = [float(v) for v in values if v is not None and math.isfinite(v)]
    n = len(vals)
    if n == 0:
        return MeanCI(math.nan, None, 0)
    mean = sum(vals) / n
    if n == 1:
        return MeanCI(mean, None, 1)
    sd = math.sqrt(sum((v - mean) ** 2 for v in vals) / (n - 1))
    return MeanCI(mean, t_quantile(n - 1) * sd / math.sqrt(n), n)


def pairs_to_resolve(d: MeanCI, effect: float, limit: int = 10**6) -> int | None:
    """The fewest values whose 95 % interval, at the spread of ``d``, has a half-width
    below ``|effect|`` (module docstring); ``None`` without a spread (``n < 2``), for a zero
    effect, or beyond ``limit``. A zero spread needs the minimum for an interval, 2."""
    if d.half is None or d.n < 2 or not math.isfinite(effect) or effect == 0:
        return None
    sd = d.half * math.sqrt(d.n) / t_quantile(d.n - 1)
    if sd == 0:
        return 2
    def narrow(n: int) -> bool:                  # t_{n-1}·sd/√n falls as n grows
        return t_quantile(n - 1) * sd / math.sqrt(n) < abs(effect)

    lo = max(2, math.ceil((1.959964 * sd / abs(effect)) ** 2))   # t > z: a lower bound
    if narrow(lo):
        return lo if lo <= limit else None
    hi = lo
    while not narrow(hi):
        lo, hi = hi, 2 * hi
        if lo > limit:
            return None
    while hi - lo > 1:                           # narrow(hi), not narrow(lo)
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if narrow(mid) else (mid, hi)
    return hi if hi <= limit else None
