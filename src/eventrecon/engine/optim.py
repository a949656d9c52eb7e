"""A run's optimiser and learning-rate schedule settings, read from its config and checked.

Each function reads one setting (``model.optim``'s lr, weight decay, eps and Adam's
betas; ``trainer``'s lr decay and warm-up), fills in its default (the authors' where they
have one) and gives one :class:`~eventrecon.common.errors.InputError` naming the key for a value
out of range or not a number, where AdamW or the schedule would otherwise fail later
with a traceback or silently train with it. :func:`eventrecon.engine.build.build_module` puts
them into the step's :class:`~eventrecon.engine.module.StepConfig`.
"""

from __future__ import annotations

import math

from omegaconf import DictConfig, OmegaConf  # noqa: F401 - OmegaConf: the doctests

from eventrecon.common.errors import InputError, as_number

__all__ = ["adam_betas", "lr_decay_start", "lr_end_factor", "lr_warmup", "optim_numbers"]


def lr_end_factor(cfg: DictConfig) -> float:
    """``trainer.lr_end_factor``: the lr at a segment's last step over its first (1 = a
    constant lr, the authors'); an :class:`InputError` unless it lies in ``(0, 1]``.

    >>> lr_end_factor(OmegaConf.create({"trainer": {}}))
    1.0
    >>> try:
    ...     lr_end_factor(OmegaConf.create({"trainer": {"lr_end_factor": 0}}))
    ... except InputError as e:
    ...     print(e.field)
    trainer.lr_end_factor
    """
    value = cfg.trainer.get("lr_end_factor", 1.0)
    f = as_number(value)
    if not 0.0 < f <= 1.0:
        raise InputError("config", "trainer.lr_end_factor", "a number in (0, 1]", value)
    return f


def lr_warmup(cfg: DictConfig) -> int:
    """``trainer.lr_warmup``: steps of the linear lr warm-up (0: none, the authors' runs);
    an :class:`InputError` unless it is an integer >= 0.

    >>> lr_warmup(OmegaConf.create({"trainer": {"lr_warmup": 27}}))
    27
    >>> try:
    ...     lr_warmup(OmegaConf.create({"trainer": {"lr_warmup": -1}}))
    ... except InputError as e:
    ...     print(e.field)
    trainer.lr_warmup
    """
    value = cfg.trainer.get("lr_warmup", 0)
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise InputError("config", "trainer.lr_warmup", "an integer number of steps >= 0",
                         value)
    return value


def lr_decay_start(cfg: DictConfig) -> float:
    """``trainer.lr_decay_start``: the share of a segment's steps before the lr starts to
    decay (0: from the first step); an :class:`InputError` unless it lies in ``[0, 1)``.

    >>> lr_decay_start(OmegaConf.create({"trainer": {"lr_decay_start": 0.6}}))
    0.6
    >>> try:
    ...     lr_decay_start(OmegaConf.create({"trainer": {"lr_decay_start": 1}}))
    ... except InputError as e:
    ...     print(e.field)
    trainer.lr_decay_start
    """
    value = cfg.trainer.get("lr_decay_start", 0.0)
    a = as_number(value)
    if not 0.0 <= a < 1.0:
        raise InputError("config", "trainer.lr_decay_start", "a number in [0, 1)", value)
    return a


def optim_numbers(cfg: DictConfig) -> tuple[float, float, float]:
    """``model.optim``'s ``(lr, weight_decay, eps)`` (defaults ``1e-3, 0, 1e-8``): an
    :class:`InputError` unless the lr and eps are finite numbers > 0 and the weight decay
    a finite number >= 0 (where AdamW's own check would stop the run with a traceback).

    >>> optim_numbers(OmegaConf.create({"model": {"optim": {"lr": 1e-4, "weight_decay": 0.1}}}))
    (0.0001, 0.1, 1e-08)
    >>> try:
    ...     optim_numbers(OmegaConf.create({"model": {"optim": {"lr": "abc"}}}))
    ... except InputError as e:
    ...     print(e.field)
    model.optim.lr
    """
    optim = cfg.model.get("optim", {}) or {}
    out = []
    for key, default, low in (("lr", 1e-3, "> 0"), ("weight_decay", 0.0, ">= 0"),
                              ("eps", 1e-8, "> 0")):
        value = optim.get(key, default)
        x = as_number(value)
        if not (math.isfinite(x) and (x > 0.0 if low == "> 0" else x >= 0.0)):
            raise InputError("config", f"model.optim.{key}", f"a finite number {low}", value)
        out.append(x)
    return out[0], out[1], out[2]


def adam_betas(cfg: DictConfig) -> tuple[float, float]:
    r"""Adam's ``(β1, β2)`` for ``cfg.model.optim``: its ``betas`` (PyTorch's ``(0.9,
    0.999)``, the authors', unless the backbone names its own) raised to the power
    ``k = betas_power`` (default 1, the authors').

    Adam's moments are moving averages with a memory of about :math:`1/(1-β)` steps. At
    ``k`` times the authors' lr every step moves the weights ``k`` times as far, so with
    :math:`β^k` the moments forget over the same distance of the path as in the authors'
    runs (:math:`(β^k)^{n/k} = β^n`). An :class:`InputError` unless ``betas`` are two
    numbers in ``[0, 1)`` and ``k > 0``.

    >>> adam_betas(OmegaConf.create({"model": {"optim": {"betas_power": 10}}}))
    (0.3486784401000001, 0.9900448802097482)
    >>> try:
    ...     adam_betas(OmegaConf.create({"model": {"optim": {"betas": [0.9]}}}))
    ... except InputError as e:
    ...     print(e.field)
    model.optim.betas
    """
    optim = cfg.model.get("optim", {}) or {}
    betas, power = optim.get("betas", [0.9, 0.999]), optim.get("betas_power", 1.0)
    try:
        b1, b2 = (float(b) for b in betas)
    except (TypeError, ValueError):
        b1 = b2 = math.nan
    if not (0.0 <= b1 < 1.0 and 0.0 <= b2 < 1.0):
        raise InputError("config", "model.optim.betas", "two numbers in [0, 1)", betas)
    k = as_number(power)
    if not k > 0.0 or not math.isfinite(k):
        raise InputError("config", "model.optim.betas_power", "a number > 0", power)
    return b1 ** k, b2 ** k
