"""Overlapping time segments of a sequence and the cross-fade between them.

Long sequences are split into overlapping segments, each with its own model, e.g.
``[0,210], [190,410], [390,610], [590,810], [790,1000]`` (time units). A render at
time ``t`` uses the segments that contain ``t``; inside an overlap ``[a, b]`` of
segments ``k`` and ``k+1`` the two linear renders are blended with the ramp

.. math:: I(t) = (1 - w) I_k(t) + w I_{k+1}(t), \\quad w = (t - a) / (b - a),

which is the authors' "decode ^2.2, linear ramp, re-encode" on saved frames.
"""

from __future__ import annotations

from collections.abc import Sequence

from eventrecon.data.batcher import Segment

__all__ = ["make_segments", "crossfade_weights", "resolve_segments"]


def make_segments(n: int, overlap: float = 20.0, span: float = 1000.0) -> list[Segment]:
    """``n`` equal segments of ``[0, span]`` overlapping by ``overlap`` time units.

    >>> [(s.start, s.end) for s in make_segments(5)]
    [(0.0, 210.0), (190.0, 410.0), (390.0, 610.0), (590.0, 810.0), (790.0, 1000.0)]
    """
    if n < 1:
        raise ValueError(f"segments: expected n ≥ 1, got {n}")
    edges = [span * k / n for k in range(n + 1)]
    half = overlap / 2
    return [Segment(max(0.0, edges[k] - half), min(span, edges[k + 1] + half)) for k in range(n)]


def resolve_segments(segments: Sequence[Sequence[float]] | None,
                     span: float = 1000.0) -> list[Segment]:
    """The segments a run trains (``[[t0, t1], ...]`` time units, sorted by start), or
    one segment ``[0, span]`` when there are none. The "w/o multi-segment" ablation sets
    ``data.segments: [[0, 1000]]``.

    >>> resolve_segments([[190, 410], [0, 210]])
    [Segment(start=0.0, end=210.0), Segment(start=190.0, end=410.0)]
    """
    if not segments:
        return [Segment(0.0, span)]
    segs = [Segment(float(a), float(b)) for a, b in segments]
    for s in segs:
        if not s.end > s.start:
            raise ValueError(f"meta.json: segments: expected start < end, got [{s.start}, {s.end}]")
    return sorted(segs, key=lambda s: s.start)


def crossfade_weights(segments: Sequence[Segment], t: float) -> list[tuple[int, float]]:
    """The segments used at time ``t`` with their blend weights (summing to 1).

    >>> segs = make_segments(2)   # [0, 510], [490, 1000]
    >>> crossfade_weights(segs, 500.0)
    [(0, 0.5), (1, 0.5)]
    >>> crossfade_weights(segs, 100.0)
    [(0, 1.0)]
    """
    inside = [i for i, s in enumerate(segments) if s.start <= t <= s.end]
    if not inside:  # outside every segment: the nearest one
        dist = [min(abs(t - s.start), abs(t - s.end)) for s in segments]
        return [(dist.index(min(dist)), 1.0)]
    if len(inside) == 1:
        return [(inside[0], 1.0)]
    a, b = inside[0], inside[-1]
    lo, hi = segments[b].start, segments[a].end
    w = 0.5 if hi <= lo else min(1.0, max(0.0, (t - lo) / (hi - lo)))
    return [(a, 1.0 - w), (b, w)]


