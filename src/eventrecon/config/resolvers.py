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

from typing import Any

from omegaconf import OmegaConf

from eventrecon.common.errors import InputError
from eventrecon.config.naming import dataset_name

__all__ = ["register_resolvers", "paper_steps", "run_data_name", "max_steps", "schedule",
           "SCHEDULES"]

#: ``trainer.schedule`` values.
SCHEDULES: tuple[str, ...] = ("paper", "compressed")


def _whole(value: Any) -> int | None:
    """``value`` as an int when it is a whole number (``1e4`` parses as a float), else
    ``None`` (a bool, text, a fraction, ``null``)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return int(value) if float(value).is_integer() else None


def max_steps(trainer: Any) -> int:
    """``trainer.max_steps``, checked: a whole number of steps ``>= 1`` (``trainer`` the
    config's ``trainer`` section), else one :class:`InputError` naming it.

    >>> max_steps({"max_steps": 9000}), max_steps({"max_steps": 1e4})
    (9000, 10000)
    """
    value = trainer.get("max_steps") if trainer is not None else None
    n = _whole(value)
    if n is None or n < 1:
        raise InputError("config", "trainer.max_steps", "an integer number of steps >= 1",
                         "null" if value is None else value)
    return n


def schedule(trainer: Any) -> tuple[str, int]:
    """``(trainer.schedule, trainer.paper_steps)``, checked: one of :data:`SCHEDULES`
    (default ``paper``) and a whole number of steps ``>= 1`` (default 150 000).

    >>> schedule({"schedule": "compressed", "paper_steps": 150000})
    ('compressed', 150000)
    """
    name = trainer.get("schedule", "paper") if trainer is not None else "paper"
    if name not in SCHEDULES:
        raise InputError("config", "trainer.schedule", " or ".join(SCHEDULES), name)
    value = trainer.get("paper_steps", 150000) if trainer is not None else 150000
    n = _whole(value)
    if n is None or n < 1:
        raise InputError("config", "trainer.paper_steps", "an integer number of steps >= 1",
                         "null" if value is None else value)
    return name, n


def paper_steps(steps: int, *, _root_: Any) -> int:
    """``steps`` of the paper's run, as ``trainer.schedule`` says (module docstring)."""
    trainer = _root_.get("trainer")
    kind, paper = schedule(trainer)
    total = max_steps(trainer)
    n = int(steps)
    if n < 0:
        raise InputError("config", "${paper_steps:...}", "a number of steps >= 0", steps)
    if kind == "paper" or n == 0:
        return n
    return max(1, int(round(n * total / paper)))


def run_data_name(*, _root_: Any) -> str:
    """``${data_name:}``: the run's data name (:func:`eventrecon.config.naming.dataset_name`),
    for the output folder."""
    data, scene = _root_.get("data") or {}, _root_.get("scene") or {}
    return dataset_name(data.get("root"), scene.get("name"))


def register_resolvers() -> None:
    """Register ``paper_steps`` and ``data_name`` (idempotent)."""
    if not OmegaConf.has_resolver("paper_steps"):
        OmegaConf.register_new_resolver("paper_steps", paper_steps)
    if not OmegaConf.has_resolver("data_name"):
        OmegaConf.register_new_resolver("data_name", run_data_name)
