"""OmegaConf resolvers used by the config tree in ``conf/``.

``${paper_steps:N}`` — a schedule of the authors' code, written in their steps: band
annealing over 4000, the NGP cylinder over 10⁴, TensoRF-CP's growth over 10⁴, out of
runs of ``trainer.paper_steps`` = 150 000 steps. It resolves to

- ``N`` with ``trainer.schedule: paper`` (the default at every scale: a short run is the
  first steps of the paper's run);
- ``round(N · trainer.max_steps / trainer.paper_steps)`` with
  ``trainer.schedule: compressed``, a named option for short CPU runs (``scale=cpu``
  uses it; the tables footnote it): the warm-up schedules keep their share of the run.

The sparsity ramp's time constant (30 000 steps) is written as a plain number: it is not
compressed, because a compressed ramp makes ``L_sparsity`` two orders of magnitude
stronger per step and the runs without ``L_acc`` collapse to the empty field.

>>> from omegaconf import OmegaConf
>>> register_resolvers()
>>> cfg = OmegaConf.create({"trainer": {"max_steps": 1500, "paper_steps": 150000,
...                                     "schedule": "paper"}, "a": "${paper_steps:4000}"})
>>> cfg.a
4000
>>> cfg.trainer.schedule = "compressed"
>>> cfg.a
40
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from omegaconf import OmegaConf

from eventrecon import TIME_SPAN
from eventrecon.errors import InputError
from eventrecon.naming import dataset_name

__all__ = ["register_resolvers", "paper_steps", "run_data_name", "max_steps", "check_run",
           "SCHEDULES"]

#: ``trainer.schedule`` values.
SCHEDULES: tuple[str, ...] = ("paper", "compressed")


def max_steps(trainer: Any) -> int:
    """``trainer.max_steps``, checked: an integer number of steps ``>= 1`` (``trainer`` the
    config's ``trainer`` section), else one :class:`InputError` naming it.

    >>> max_steps({"max_steps": 9000})
    9000
    """
    value = trainer.get("max_steps") if trainer is not None else None
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise InputError("config", "trainer.max_steps", "an integer number of steps >= 1",
                         "missing" if value is None else value)
    return int(value)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and math.isfinite(value))


def check_run(cfg: Any) -> None:
    """The run-level keys a typo would otherwise stop deep inside training with a
    traceback, checked before any data is read: ``trainer.max_steps`` (:func:`max_steps`),
    ``seed`` (an integer), ``trainer.n_rays`` (an integer >= 1), and of ``data``:
    ``segment`` (``null`` or an integer >= 0) and ``views`` (``null`` or an integer >= 1),
    whose upper bounds are the dataset's and are checked once it is read, ``fps``
    (``null`` or a number > 0), ``neg_ratio`` (a number in ``[0, 1]``) and ``window``
    (``null`` or ``[t0, t1]`` time units, ``0 <= t0 < t1 <= 1000``). One
    :class:`InputError` for the first that is wrong.

    >>> check_run({"trainer": {"max_steps": 5, "n_rays": 256}, "seed": 0,
    ...            "data": {"segment": None}})
    >>> try:
    ...     check_run({"trainer": {"max_steps": 5, "n_rays": 0}, "seed": 0, "data": {}})
    ... except InputError as e:
    ...     print(e.field)
    trainer.n_rays
    """
    max_steps(cfg.get("trainer"))
    seed = cfg.get("seed", 0)
    if not _is_int(seed):
        raise InputError("config", "seed", "an integer", seed)
    data = cfg.get("data") or {}
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
        raise InputError("config", "data.neg_ratio", "a fraction in [0, 1]", neg)
    window = data.get("window")
    if window is not None and not (
            isinstance(window, Sequence) and not isinstance(window, str) and len(window) == 2
            and all(_is_number(x) for x in window)
            and 0.0 <= window[0] < window[1] <= TIME_SPAN):
        raise InputError("config", "data.window",
                         f"null or [t0, t1] time units with 0 <= t0 < t1 <= {TIME_SPAN:g}",
                         list(window) if isinstance(window, Sequence)
                         and not isinstance(window, str) else window)
    n_rays = cfg["trainer"].get("n_rays", 256)
    if not (_is_int(n_rays) and n_rays >= 1):
        raise InputError("config", "trainer.n_rays", "an integer number of rays >= 1", n_rays)


def paper_steps(steps: int, *, _root_: Any) -> int:
    """``steps`` of the paper's run, as ``trainer.schedule`` says (module docstring)."""
    trainer = _root_.get("trainer")
    total = max_steps(trainer)
    schedule = str(trainer.get("schedule", "paper"))
    paper = int(trainer.get("paper_steps", 150000))
    if schedule not in SCHEDULES:
        raise InputError("config", "trainer.schedule", " or ".join(SCHEDULES), schedule)
    n = int(steps)
    if n < 0:
        raise InputError("config", "${paper_steps:...}", "a number of steps >= 0", steps)
    if schedule == "paper" or n == 0:
        return n
    return max(1, int(round(n * total / paper)))


def run_data_name(*, _root_: Any) -> str:
    """``${data_name:}``: the run's data name (:func:`eventrecon.naming.dataset_name`),
    for the output folder."""
    data, scene = _root_.get("data") or {}, _root_.get("scene") or {}
    return dataset_name(data.get("root"), scene.get("name"))


def register_resolvers() -> None:
    """Register ``paper_steps`` and ``data_name`` (idempotent)."""
    if not OmegaConf.has_resolver("paper_steps"):
        OmegaConf.register_new_resolver("paper_steps", paper_steps)
    if not OmegaConf.has_resolver("data_name"):
        OmegaConf.register_new_resolver("data_name", run_data_name)
