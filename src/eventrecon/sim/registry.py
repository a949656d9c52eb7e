"""Sensor effects as small named units, built from the scene's ordered lists.

A scene lists ``events: [{name: shot_noise, rate_hz: 0.5}, ...]`` and
``frames: [{name: crf, eps: 0.03}, ...]``. :meth:`Registry.build` turns such a list into
effect instances, in order: a misspelt name lists the valid ones, an unknown or invalid
parameter names the scene field (``events[1].rate_hz``). Nothing else is constructed,
so an unlisted effect never runs and never draws a random number.

An effect class declares its parameters as ``PARAMS = {name: Param(...)}``; the base
class reads and checks them (``self.p[name]``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from eventrecon.common.errors import InputError
from eventrecon.sim.config import MISSING, get

__all__ = ["Param", "Effect", "Registry", "positive", "non_negative"]


def positive(v: float) -> bool:
    return v > 0


def non_negative(v: float) -> bool:
    return v >= 0


@dataclass(frozen=True)
class Param:
    """One effect parameter: accepted type, default (``MISSING`` = required), check."""

    kind: type | tuple[type, ...] = float
    default: Any = MISSING
    check: Callable[[Any], bool] | None = None
    expect: str | None = None
    doc: str = ""


class Effect:
    """Base of all effects: parameter parsing, name, position in the list.

    Attributes:
        name: registry key; PARAMS: parameter specs; stage: ``"signal"`` (configures
            the event core) or ``"stream"`` (transforms arrays) -- frame effects are all
            ``"stream"``; first_only: must be the first effect of its list.
        p: parsed parameters; index: position in the scene list; occurrence: how many
            earlier effects of the same name precede it (part of its random seed).
    """

    name: ClassVar[str] = ""
    PARAMS: ClassVar[dict[str, Param]] = {}
    stage: ClassVar[str] = "stream"
    first_only: ClassVar[bool] = False

    def __init__(self, raw: Mapping, where: str, prefix: str, index: int = 0,
                 occurrence: int = 0):
        self.where, self.prefix, self.index, self.occurrence = where, prefix, index, occurrence
        unknown = sorted(set(raw) - set(self.PARAMS) - {"name"})
        if unknown:
            raise InputError(where, f"{prefix}{unknown[0]}",
                             f"a parameter of {self.name} ({', '.join(self.PARAMS) or 'none'})",
                             "unknown")
        self.p = {k: get(raw, k, s.kind, where, prefix, default=s.default, check=s.check,
                         expect=s.expect) for k, s in self.PARAMS.items()}

    def config(self) -> dict:
        """``{"name": ..., **params}`` as recorded in the dataset metadata."""
        return {"name": self.name, **self.p}

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.p})"


class Registry:
    """Name → effect class, for one side (``events`` or ``frames``)."""

    def __init__(self, side: str):
        self.side = side
        self.classes: dict[str, type[Effect]] = {}

    def register(self, cls: type[Effect]) -> type[Effect]:
        """Class decorator adding ``cls`` under ``cls.name``."""
        self.classes[cls.name] = cls
        return cls

    def build(self, raw: object, where: str) -> list[Effect]:
        """Effects of the scene list ``raw`` (``None`` = no effects), in order."""
        if raw is None:
            return []
        if not isinstance(raw, list):
            raise InputError(where, self.side, "a list of {name: ..., params} entries",
                             type(raw).__name__)
        out: list[Effect] = []
        counts: dict[str, int] = {}
        for i, item in enumerate(raw):
            pre = f"{self.side}[{i}]."
            name = get(item, "name", str, where, pre, check=lambda v: v in self.classes,
                       expect="one of " + ", ".join(sorted(self.classes)))
            cls = self.classes[name]
            if cls.first_only and i != 0:
                raise InputError(where, f"{pre}name", f"{name} as the first {self.side} effect",
                                 f"position {i}")
            if cls.stage == "signal" and any(e.stage == "stream" for e in out):
                raise InputError(where, f"{pre}name",
                                 f"{name} (acts on the log signal before crossing detection) "
                                 "listed before every event-stream effect", f"position {i}")
            out.append(cls(item, where, pre, i, counts.get(name, 0)))
            counts[name] = counts.get(name, 0) + 1
        return out
