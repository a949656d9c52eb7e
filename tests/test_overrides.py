"""Overrides Hydra fails to apply: the override named in one line (eventrecon.overrides)."""

from __future__ import annotations

import types

import pytest

from eventrecon.overrides import bad_override, override_in_flight, report_bad_overrides


def _apply_overrides_to_config(line: str) -> None:   # Hydra's name, for the frame walk
    override = types.SimpleNamespace(input_line=line)  # noqa: F841 - read from the frame
    int("type")


def test_the_override_being_applied_is_read_from_hydras_frame():
    with pytest.raises(ValueError) as err:
        _apply_overrides_to_config("scene.objects.0.motion.type=spin")
    assert override_in_flight(err.value.__traceback__) == "scene.objects.0.motion.type=spin"


def test_an_error_raised_elsewhere_names_no_override():
    with pytest.raises(ValueError) as err:
        int("type")
    assert override_in_flight(err.value.__traceback__) is None
    assert override_in_flight(None) is None


def test_the_line_names_the_key_the_override_and_the_error():
    assert str(bad_override(ValueError("bad"), "a.0.b=1")) == (
        "command line: a.0.b: expected a key naming a path of the config (a list's items by "
        "their index, e.g. motion.0.type where motion is a list), got a.0.b=1 (ValueError: bad)")


def test_the_wrap_is_made_once():
    from hydra._internal.config_loader_impl import ConfigLoaderImpl

    assert report_bad_overrides() and report_bad_overrides()
    step = ConfigLoaderImpl._apply_overrides_to_config
    assert step._reports_bad_overrides and step.__closure__ is not None
    inner = [c.cell_contents for c in step.__closure__ if callable(c.cell_contents)]
    assert not any(getattr(f, "_reports_bad_overrides", False) for f in inner)
