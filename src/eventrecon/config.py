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

from eventrecon.errors import InputError
from eventrecon.naming import dataset_name

__all__ = ["register_resolvers", "paper_steps", "run_data_name", "max_steps", "SCHEDULES"]

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
