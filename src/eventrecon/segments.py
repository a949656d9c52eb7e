"""Multi-segment training: overlapping time segments and the cross-fade between them.

Long sequences are split into overlapping segments, each with its own model, e.g.
``[0,210], [190,410], [390,610], [590,810], [790,1000]`` (time units). A render at time
``t`` uses the segments that contain ``t``; inside an overlap ``[a, b]`` of segments
``k`` and ``k+1`` the two linear renders are blended with the ramp

.. math:: I(t) = (1 - w) I_k(t) + w I_{k+1}(t), \\quad w = (t - a) / (b - a),

which is the authors' "decode ^2.2, linear ramp, re-encode" on saved frames.

Every segment trains ``trainer.max_steps`` steps (the authors' multi-segment runs);
``trainer.split_steps=true`` divides that budget over the segments instead (equal
compute for any number of segments), and each segment's config has its own
``max_steps`` so schedules written as fractions of the run fit the segment.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from omegaconf import DictConfig, OmegaConf

from eventrecon.config import max_steps
from eventrecon.data.batcher import Segment

__all__ = ["make_segments", "crossfade_weights", "resolve_segments", "segment_steps",
           "segment_config", "run_window", "run_segments"]


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


def segment_steps(cfg: DictConfig, n_segments: int) -> int:
    """Optimiser steps of each segment: ``trainer.max_steps`` (checked,
    :func:`~eventrecon.config.max_steps`), or with ``trainer.split_steps=true`` the run's
    budget ``ceil(max_steps / n_segments)``.

    >>> segment_steps(OmegaConf.create({"trainer": {"max_steps": 1000, "split_steps": True}}), 3)
    334
    """
    total = max_steps(cfg.trainer)
    return math.ceil(total / n_segments) if cfg.trainer.get("split_steps") else total


def segment_config(cfg: DictConfig, steps: int) -> DictConfig:
    """``cfg`` with ``trainer.max_steps`` = the segment's own steps, so that schedules written
    compressed to the run (``${paper_steps:N}`` with ``trainer.schedule=compressed``) take
    the shape of the run each model trains."""
    if int(cfg.trainer.max_steps) == steps and not cfg.trainer.get("split_steps"):
        return cfg
    return OmegaConf.merge(cfg, {"trainer": {"max_steps": steps, "split_steps": False}})


def run_window(cfg: DictConfig) -> tuple[float, float] | None:
    """The run's ``data.window`` as ``(t0, t1)`` time units, or ``None``."""
    window = cfg.data.get("window")
    return (float(window[0]), float(window[1])) if window else None


def run_segments(cfg: DictConfig, dataset_segments: Sequence[Sequence[float]] | None
                 ) -> list[Segment]:
    """The segments a run trains: ``data.segments`` when set, else the ``data.window``
    alone when set, else the dataset's (``dataset_segments``, which already has
    ``data.segments`` applied over ``meta.json``)."""
    window = run_window(cfg)
    explicit = cfg.data.get("segments") is not None
    return resolve_segments(dataset_segments if explicit or window is None else [window])
