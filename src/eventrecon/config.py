"""OmegaConf resolvers used by the config tree in ``conf/``.

``${of_run:f}`` — a schedule length written as a fraction ``f`` of the run: it resolves to
``round(f · trainer.max_steps)`` steps. The paper's schedules are given in iterations of
its 150k-step run (band annealing over 4000, the sparsity ramp's 30000); written as
fractions (``${of_run:0.0266667}``, ``${of_run:0.2}``) they are exactly the paper's
values under ``trainer=paper`` and keep their shape in a 1500-step CPU run, where 4000
absolute steps would leave most positional-encoding bands switched off.

>>> from omegaconf import OmegaConf
>>> register_resolvers()
>>> cfg = OmegaConf.create({"trainer": {"max_steps": 150000}, "ramp": "${of_run:0.2}"})
>>> cfg.ramp
30000
"""

from __future__ import annotations

from typing import Any

from omegaconf import OmegaConf

from eventrecon.errors import InputError

__all__ = ["register_resolvers", "of_run"]


def of_run(fraction: float, *, _root_: Any) -> int:
    """``round(fraction · trainer.max_steps)`` of the config ``_root_``."""
    try:
        total = int(_root_.trainer.max_steps)
    except Exception:  # noqa: BLE001 - no trainer section: a config outside train.py
        raise InputError("config", "trainer.max_steps",
                         "an integer (needed by ${of_run:...})", "missing") from None
    f = float(fraction)
    if not 0.0 <= f <= 1.0:
        raise InputError("config", "${of_run:...}", "a fraction of the run in [0, 1]", fraction)
    return int(round(f * total))


def register_resolvers() -> None:
    """Register ``of_run`` (idempotent)."""
    if not OmegaConf.has_resolver("of_run"):
        OmegaConf.register_new_resolver("of_run", of_run)
