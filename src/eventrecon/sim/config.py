"""Reading and validating scene-config values, seeds and config hashes.

Every simulator module reads its YAML fields through :func:`get`, so a malformed value
raises one :class:`~eventrecon.common.errors.InputError` naming the scene file and the dotted
field (``scene spheres: objects[1].motion.turns: expected a number, got 'two'``).

Random streams are derived, never global: :func:`effect_rng` seeds a NumPy generator
from ``(scene seed, side/effect name, occurrence, view)``, so adding, removing or
reordering one effect leaves the random numbers of every other effect unchanged.
"""

from __future__ import annotations

import hashlib
import json
import zlib
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from eventrecon.common.errors import InputError

__all__ = ["get", "get_vec", "positive", "effect_rng", "config_hash", "to_plain", "MISSING"]

#: Marker for a required field (no default).
MISSING: Any = object()


def to_plain(cfg: Any) -> Any:
    """A resolved plain ``dict``/``list`` copy of a ``DictConfig``, ``dict`` or list."""
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf
        if isinstance(cfg, (DictConfig, ListConfig)):
            return OmegaConf.to_container(cfg, resolve=True)
    except ImportError:  # pragma: no cover - omegaconf is a dependency
        pass
    if isinstance(cfg, Mapping):
        return {str(k): to_plain(v) for k, v in cfg.items()}
    if isinstance(cfg, (list, tuple)):
        return [to_plain(v) for v in cfg]
    return cfg


def get(cfg: Mapping, key: str, kind: type | tuple[type, ...], where: str, prefix: str = "",
        default: Any = MISSING, check: Callable[[Any], bool] | None = None,
        expect: str | None = None) -> Any:
    """Read ``cfg[key]``, check its type and an optional predicate.

    Args:
        cfg: the mapping holding the field.
        key: field name; reported as ``prefix + key``.
        kind: accepted Python type(s); ``float`` also accepts ``int`` (not ``bool``).
        where: the file or scene the config came from (first part of the error).
        default: value when the key is absent (required when :data:`MISSING`).
        check: predicate on the value; ``False`` raises with ``expect``.
        expect: the expectation an error states; by default the type's name (``an
            integer``) and the check's ``rule`` attribute (``> 0``, :func:`positive`).

    >>> get({"theta": 0.5}, "theta", float, "scene x", check=lambda v: v > 0)
    0.5
    """
    field = f"{prefix}{key}"
    if not isinstance(cfg, Mapping):
        raise InputError(where, prefix.rstrip(".") or "<root>", "a mapping", type(cfg).__name__)
    if key not in cfg or cfg[key] is None:
        if default is MISSING:
            raise InputError(where, field, expect or _expected(kind, check), "missing")
        return default
    value = cfg[key]
    kinds = kind if isinstance(kind, tuple) else (kind,)
    if float in kinds and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if ((isinstance(value, bool) and bool not in kinds) or not isinstance(value, kinds)
            or (check is not None and not check(value))):
        raise InputError(where, field, expect or _expected(kind, check), repr(value))
    return value


def _expected(kind: type | tuple[type, ...], check: Callable[[Any], bool] | None) -> str:
    """The default expectation of :func:`get`: ``an integer``, ``a number > 0`` (the
    check's ``rule``, :func:`positive`)."""
    name = _kind_name(kind)
    text = f"{'an' if name[0] in 'aeiou' else 'a'} {name}"
    return text if check is None else f"{text} {getattr(check, 'rule', 'that passes its check')}"


def positive(v: float) -> bool:
    """The check ``v > 0`` (its ``rule`` is what an error says it expects)."""
    return v > 0


positive.rule = "> 0"  # type: ignore[attr-defined]


def get_vec(cfg: Mapping, key: str, n: int, where: str, prefix: str = "",
            default: Sequence[float] | None = None) -> np.ndarray:
    """Read a list of ``n`` numbers as a float64 array ``[n]``."""
    raw = get(cfg, key, (list, tuple), where, prefix,
              default=MISSING if default is None else list(default),
              expect=f"a list of {n} numbers")
    if len(raw) != n or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                for v in raw):
        raise InputError(where, f"{prefix}{key}", f"a list of {n} numbers", repr(raw))
    return np.asarray(raw, dtype=np.float64)


def _kind_name(kind: type | tuple[type, ...]) -> str:
    names = {float: "number", int: "integer", str: "string", bool: "boolean",
             list: "list", tuple: "list", dict: "mapping"}
    kinds = kind if isinstance(kind, tuple) else (kind,)
    return " or ".join(dict.fromkeys(names.get(k, k.__name__) for k in kinds))


def effect_rng(seed: int, side: str, name: str, occurrence: int = 0,
               *ids: int) -> np.random.Generator:
    """The independent generator of one effect instance on one view / frame.

    Seeded by ``SeedSequence([seed, crc32(side/name), occurrence, *ids])`` (``ids`` e.g.
    the view and frame index): the stream depends only on the scene seed and the
    effect's own identity, never on which other effects are listed (so an unlisted
    effect draws nothing and perturbs nobody).
    """
    key = zlib.crc32(f"{side}/{name}".encode())
    return np.random.default_rng(np.random.SeedSequence(
        [int(seed) & 0xFFFFFFFF, key, int(occurrence), *(int(i) for i in ids)]))


def config_hash(cfg: Any, version: int, n: int = 10) -> str:
    """First ``n`` hex digits of SHA-256 over the canonical JSON of ``(version, cfg)``."""
    blob = json.dumps({"version": version, "cfg": to_plain(cfg)}, sort_keys=True,
                      separators=(",", ":"), default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:n]
