"""Command-line overrides that Hydra fails to apply, reported in one line.

Hydra reports OmegaConf's errors about an override in a line or two (``Could not override
'trainer.nonexistent_key'``), but a few errors escape it as a full Python traceback. The
common one is a list addressed by a name: ``scene.objects.0.motion.type=orbit`` where that
object's ``motion`` is a list of motions (``motion.0.type`` was meant); OmegaConf then
raises ``ValueError: invalid literal for int()``. :func:`report_bad_overrides` makes
Hydra report such an error as it reports its own: the project's one-line
:class:`~eventrecon.errors.InputError` message naming the override, no traceback, exit
status 1 (Hydra's, as for any override it refuses).
"""

from __future__ import annotations

from collections.abc import Callable
from types import TracebackType

from eventrecon.errors import InputError

__all__ = ["override_in_flight", "report_bad_overrides"]

#: The Hydra function that applies the command line's overrides to the composed config.
_APPLY = "_apply_overrides_to_config"


def override_in_flight(tb: TracebackType | None) -> str | None:
    """The override, as typed, that Hydra was applying where the traceback ``tb`` was
    raised; ``None`` when the error came from anywhere else."""
    while tb is not None:
        frame = tb.tb_frame
        if frame.f_code.co_name == _APPLY:
            line = getattr(frame.f_locals.get("override"), "input_line", None)
            return str(line) if line is not None else None
        tb = tb.tb_next
    return None


def bad_override(err: BaseException, line: str) -> InputError:
    """The one-line error for the override ``line`` that failed with ``err``."""
    return InputError("command line", line.split("=", 1)[0],
                      "a key naming a path of the config (a list's items by their index, "
                      "e.g. motion.0.type where motion is a list)",
                      f"{line} ({type(err).__name__}: {err})")


def report_bad_overrides() -> bool:
    """Wrap Hydra's override step so that a plain Python error raised while it applies an
    override becomes Hydra's compact error (:func:`bad_override`'s line) instead of a
    traceback. Idempotent; returns whether the step is wrapped (``False`` where this Hydra
    has no such step: its errors are then left as they are)."""
    try:
        from hydra._internal.config_loader_impl import ConfigLoaderImpl
        from hydra.errors import ConfigCompositionException
    except ImportError:                          # pragma: no cover - another Hydra
        return False
    apply: Callable | None = getattr(ConfigLoaderImpl, _APPLY, None)
    if apply is None:                            # pragma: no cover - another Hydra
        return False
    if getattr(apply, "_reports_bad_overrides", False):
        return True

    def wrapped(overrides, cfg) -> None:         # noqa: ANN001 - Hydra's own types
        try:
            apply(overrides, cfg)
        except (ValueError, TypeError, IndexError, KeyError) as err:
            line = override_in_flight(err.__traceback__)
            if line is None:
                raise
            raise ConfigCompositionException(str(bad_override(err, line))) from None

    wrapped._reports_bad_overrides = True        # type: ignore[attr-defined]
    setattr(ConfigLoaderImpl, _APPLY, staticmethod(wrapped))
    return True
