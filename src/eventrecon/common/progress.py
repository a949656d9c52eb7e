"""Progress of counted work outside training, as log lines with a rate and time left.

Kept free of Lightning and torch so the simulator and the dataset reader can use it:
one line about every ``every_s`` seconds, never a carriage-return bar (its output goes to
terminals, files and sweep logs alike)::

    rendering frames: 40/126 (32%)  0.84 s each  eta 1m12s
"""

from __future__ import annotations

import logging
import math
import time

__all__ = ["TaskProgress", "format_seconds"]

log = logging.getLogger("eventrecon.engine.progress")


def format_seconds(s: float) -> str:
    """``3725 -> '1h02m'``, ``61 -> '1m01s'``, ``5.2 -> '5s'``.

    >>> format_seconds(3725), format_seconds(61), format_seconds(5.2), format_seconds(float("nan"))
    ('1h02m', '1m01s', '5s', '?')
    """
    if not math.isfinite(s):
        return "?"
    s = max(0.0, s)
    if s >= 3600:
        return f"{int(s // 3600)}h{int(s % 3600 // 60):02d}m"
    if s >= 60:
        return f"{int(s // 60)}m{int(s % 60):02d}s"
    return f"{s:.0f}s"


class TaskProgress:
    """Progress of a counted task outside training: a line about every ``every_s``
    seconds (``done/total``, rate, time left), or nothing for short tasks.

    >>> p = TaskProgress("evaluation", 3, every_s=0.0)
    >>> p.step(); p.step(); p.step()
    """

    def __init__(self, what: str, total: int, every_s: float = 30.0) -> None:
        self.what, self.total, self.every_s = what, int(total), float(every_s)
        self.done = 0
        self._t0 = self._last = time.perf_counter()

    def step(self, n: int = 1) -> None:
        """``n`` more units done; log a line when one is due."""
        self.done += n
        now = time.perf_counter()
        if now - self._last < self.every_s and self.done < self.total:
            return
        self._last = now
        rate = (now - self._t0) / max(self.done, 1)
        if self.done < self.total or now - self._t0 >= self.every_s:
            log.info("%s: %d/%d (%.0f%%)  %.2f s each  eta %s", self.what, self.done,
                     self.total, 100.0 * self.done / max(self.total, 1), rate,
                     format_seconds((self.total - self.done) * rate))
