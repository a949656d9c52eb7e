"""The event array of one camera view.

Compact dtypes: x, y int16 pixel column / row; t float64 time units in [0, 1000]
(float32 would lose resolution: 1000 units in 24 bits is 6e-5 units); p int8 (±1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["EventStream"]


@dataclass
class EventStream:
    """The events of one view, sorted by time.

    Attributes:
        x, y: ``[N]`` int16 pixel column / row.
        t: ``[N]`` float64 time units in [0, 1000], non-decreasing.
        p: ``[N]`` int8 polarity in {−1, +1}.

    >>> len(EventStream.empty())
    0
    """

    x: np.ndarray
    y: np.ndarray
    t: np.ndarray
    p: np.ndarray

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @staticmethod
    def empty() -> EventStream:
        return EventStream(np.zeros(0, np.int16), np.zeros(0, np.int16),
                           np.zeros(0, np.float64), np.zeros(0, np.int8))
