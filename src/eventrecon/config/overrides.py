"""Command-line overrides that Hydra fails to apply, reported in one line.

Hydra reports OmegaConf's errors about an override in a line or two (``Could not override
'trainer.nonexistent_key'``), but a few errors escape it as a full Python traceback. The
common one is a list addressed by a name: ``scene.objects.0.motion.type=orbit`` where that
object's ``motion`` is a list of motions (``motion.0.type`` was meant); OmegaConf then
raises ``ValueError: invalid literal for int()``. :func:`report_bad_overrides` makes
Hydra report such an error as it reports its own: the project's one-line
:class:`~eventrecon.common.errors.InputError` message naming the override and the list, no
traceback (``HYDRA_FULL_ERROR=1`` still shows it), exit status 1 (Hydra's, as for any
override it refuses).
"""

from __future__ import annotations

import inspect
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from eventrecon.common.errors import InputError

__all__ = ["bad_override", "list_node", "override_in_flight", "report_bad_overrides"]

#: The Hydra function that applies the command line's overrides to the composed config.
_APPLY = "_apply_overrides_to_config"


def override_in_flight(tb: Any) -> Any | None:
    """The override Hydra was applying (its ``Override``: ``input_line``,
    ``key_or_group``) where the traceback ``tb`` was raised; ``None`` when the error came
    from anywhere else."""
    while tb is not None:
        frame = tb.tb_frame
        if frame.f_code.co_name == _APPLY:
            override = frame.f_locals.get("override")
            return override if getattr(override, "input_line", None) is not None else None
        tb = tb.tb_next
    return None


def list_node(cfg: DictConfig, key: str) -> str | None:
    """The longest prefix of the dotted ``key`` that names a list in ``cfg`` and is
    followed by a part that is no index, e.g. ``scene.objects.0.motion`` for
    ``scene.objects.0.motion.type``; ``None`` when there is none.

    >>> list_node(OmegaConf.create({"a": [{"m": [1]}]}), "a.0.m.type")
    'a.0.m'
    """
    parts = key.split(".")
    for k in range(len(parts) - 1, 0, -1):
        node = OmegaConf.select(cfg, ".".join(parts[:k]), throw_on_missing=False)
        if isinstance(node, ListConfig) and not parts[k].lstrip("-").isdigit():
            return ".".join(parts[:k])
    return None


def bad_override(err: BaseException, line: str, key: str, listed: str | None = None
                 ) -> InputError:
    """The one-line error for the override ``line`` (of ``key``) that failed with
    ``err``; ``listed``: the list it addressed by a name (:func:`list_node`)."""
    if listed is not None:
        rest = key[len(listed) + 1:]
        expected = (f"{listed}'s items addressed by their index ({listed} is a list), "
                    f"e.g. {listed}.0.{rest}")
    else:
        expected = "a key naming a path of the config"
    return InputError("command line", key, expected, f"{line} ({type(err).__name__}: {err})")


def report_bad_overrides() -> bool:
    """Wrap Hydra's override step so that a plain Python error raised while it applies an
    override becomes Hydra's compact error (:func:`bad_override`'s line) instead of a
    traceback. Idempotent; returns whether the step is wrapped (``False`` where this Hydra
    has no such static step: its errors are then left as they are)."""
    try:
        from hydra._internal.config_loader_impl import ConfigLoaderImpl
        from hydra.errors import ConfigCompositionException
    except ImportError:                          # pragma: no cover - another Hydra
        return False
    if not isinstance(inspect.getattr_static(ConfigLoaderImpl, _APPLY, None), staticmethod):
        return False                             # pragma: no cover - another Hydra
    apply = getattr(ConfigLoaderImpl, _APPLY)
    if getattr(apply, "_reports_bad_overrides", False):
        return True

    def wrapped(*args: Any, **kwargs: Any) -> Any:
        try:
            return apply(*args, **kwargs)
        except (ValueError, TypeError, IndexError, KeyError) as err:
            override = override_in_flight(err.__traceback__)
            if override is None:
                raise
            key = str(override.key_or_group)
            cfg = args[1] if len(args) > 1 else kwargs.get("cfg")
            listed = list_node(cfg, key) if isinstance(cfg, DictConfig) else None
            raise ConfigCompositionException(
                str(bad_override(err, override.input_line, key, listed))) from err

    wrapped._reports_bad_overrides = True        # type: ignore[attr-defined]
    setattr(ConfigLoaderImpl, _APPLY, staticmethod(wrapped))
    return True
