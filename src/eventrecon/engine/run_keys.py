"""The run-level config keys, checked before a run reads or simulates any data.

A typo in one of these used to stop a run deep inside with a traceback: Lightning's own
checks of ``max_steps`` and ``precision``, AdamW's of the lr and weight decay,
``int('abc')`` for a segment index or a layer count, an ``IndexError`` for zero rays, a
window error blamed on ``meta.json``. :func:`check_run_keys` gives one
:class:`InputError` naming the key, what it expects and the value, before the run reads
its dataset (a scene not yet simulated would be simulated first) or writes anything
(under ``train.py`` Hydra has made the job's folder already; a sweep records the failure
there). Keys whose bounds depend on the dataset (``data.views`` at most the dataset's
views, ``data.segment`` below its segment count, ``data.fps`` at most its frame rate)
get their upper bounds checked once it is read.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from eventrecon import TIME_SPAN
from eventrecon.common.errors import InputError, as_number
from eventrecon.config.precision import run_precision
from eventrecon.config.resolvers import max_steps, schedule
from eventrecon.engine.build import DESCRIPTIVE_KEYS, target_and_arguments
from eventrecon.engine.losses import LossConfig
from eventrecon.engine.optim import (
    adam_betas,
    lr_decay_start,
    lr_end_factor,
    lr_warmup,
    optim_numbers,
)
from eventrecon.fields.base import Field
from eventrecon.render.renderer import Renderer

__all__ = ["check_run_keys", "check_data_keys"]


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return math.isfinite(as_number(value))


def _is_list(value: Any) -> bool:
    return isinstance(value, Sequence) and not isinstance(value, str)


def check_data_keys(data: Mapping[str, Any]) -> None:
    """``data.segment`` (``null`` or an integer >= 0), ``views`` (``null`` or an integer
    >= 1), ``fps`` (``null`` or a number > 0), ``neg_ratio`` (a number in ``[0, 1]``) and
    ``window`` (``null`` or ``[t0, t1]`` time units, ``0 <= t0 < t1 <= 1000``).

    >>> check_data_keys({"segment": None, "views": 3, "fps": 0.5, "neg_ratio": 0.9,
    ...                  "window": [90, 210]})
    >>> try:
    ...     check_data_keys({"window": [500, 100]})
    ... except InputError as e:
    ...     print(e.field, e.got)
    data.window [500, 100]
    """
    segment = data.get("segment")
    if segment is not None and not (_is_int(segment) and segment >= 0):
        raise InputError("config", "data.segment", "null (every segment) or an integer >= 0",
                         segment)
    views = data.get("views")
    if views is not None and not (_is_int(views) and views >= 1):
        raise InputError("config", "data.views", "null (every view) or an integer >= 1", views)
    fps = data.get("fps")
    if fps is not None and not (_is_number(fps) and fps > 0):
        raise InputError("config", "data.fps", "null (every frame) or a frame rate > 0", fps)
    neg = data.get("neg_ratio", 0.0)
    if not (_is_number(neg) and 0.0 <= neg <= 1.0):
        raise InputError("config", "data.neg_ratio", "a fraction in [0, 1]",
                         "null" if neg is None else neg)
    window = data.get("window") or None               # [] as null: no window, as before
    if window is not None and not (_is_list(window) and len(window) == 2
                                   and all(_is_number(x) for x in window)
                                   and 0.0 <= window[0] < window[1] <= TIME_SPAN):
        raise InputError("config", "data.window",
                         f"null or [t0, t1] time units with 0 <= t0 < t1 <= {TIME_SPAN:g}",
                         list(window) if _is_list(window) else window)


def check_run_keys(cfg: Mapping[str, Any]) -> None:
    """Every key of the module docstring, the first wrong one as one :class:`InputError`:

    - ``trainer``: ``schedule`` and ``paper_steps`` (:func:`~eventrecon.config.resolvers.schedule`),
      ``max_steps`` (:func:`~eventrecon.config.resolvers.max_steps`), ``n_rays`` (an integer >= 1),
      the lr schedule (:mod:`eventrecon.engine.optim`) and the precision
      (:func:`~eventrecon.config.precision.run_precision`);
    - ``seed`` (an integer) and the ``data`` keys (:func:`check_data_keys`);
    - ``model.optim``'s numbers and betas (:mod:`eventrecon.engine.optim`);
    - ``model``, ``loss`` and ``render``: their targets import and their values have the
      types their constructors declare (:func:`~eventrecon.engine.build.target_and_arguments`,
      nothing built).

    >>> from omegaconf import OmegaConf
    >>> ok = {"trainer": {"max_steps": 5, "n_rays": 256, "lightning": {"precision": 32}},
    ...       "seed": 0, "data": {}, "model": {"optim": {"lr": 1e-3}}}
    >>> check_run_keys(OmegaConf.create(ok))
    >>> try:
    ...     check_run_keys(OmegaConf.merge(ok, {"trainer": {"n_rays": 0}}))
    ... except InputError as e:
    ...     print(e.field)
    trainer.n_rays
    """
    trainer = cfg.get("trainer")
    schedule(trainer)
    max_steps(trainer)
    seed = cfg.get("seed", 0)
    if not _is_int(seed):
        raise InputError("config", "seed", "an integer", seed)
    n_rays = trainer.get("n_rays", 256)
    if not (_is_int(n_rays) and n_rays >= 1):
        raise InputError("config", "trainer.n_rays", "an integer number of rays >= 1", n_rays)
    check_data_keys(cfg.get("data") or {})
    optim_numbers(cfg)
    adam_betas(cfg)
    lr_end_factor(cfg)
    lr_warmup(cfg)
    lr_decay_start(cfg)
    run_precision(cfg)
    for key, base, skip in (("model", Field, DESCRIPTIVE_KEYS),
                            ("loss", LossConfig, DESCRIPTIVE_KEYS),
                            ("render", Renderer, ("image_autocast",))):
        node = cfg.get(key)
        if node is not None and node.get("_target_"):
            target_and_arguments(node, key, base, skip)
