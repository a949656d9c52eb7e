"""Multi-segment training: each segment's step budget and config, and a run's segments.

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

from eventrecon.config.resolvers import max_steps
from eventrecon.data.batcher import Segment
from eventrecon.data.segments import resolve_segments

__all__ = ["segment_steps", "segment_config", "run_window", "run_segments"]


def segment_steps(cfg: DictConfig, n_segments: int) -> int:
    """Optimiser steps of each segment: ``trainer.max_steps`` (checked,
    :func:`~eventrecon.config.resolvers.max_steps`), or with ``trainer.split_steps=true`` the run's
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
