"""Overrides Hydra fails to apply: the override named in one line (eventrecon.config.overrides)."""

from __future__ import annotations

import types
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra._internal.config_loader_impl import ConfigLoaderImpl
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from eventrecon.config.overrides import (
    bad_override,
    list_node,
    override_in_flight,
    report_bad_overrides,
)

CONF = Path(__file__).resolve().parents[1] / "conf"


def _apply_overrides_to_config(line: str) -> None:   # Hydra's name, for the frame walk
    override = types.SimpleNamespace(input_line=line)  # noqa: F841 - read from the frame
    int("type")


def test_the_override_being_applied_is_read_from_hydras_frame():
    with pytest.raises(ValueError) as err:
        _apply_overrides_to_config("scene.objects.0.motion.type=spin")
    found = override_in_flight(err.value.__traceback__)
    assert found.input_line == "scene.objects.0.motion.type=spin"


def test_an_error_raised_elsewhere_names_no_override():
    with pytest.raises(ValueError) as err:
        int("type")
    assert override_in_flight(err.value.__traceback__) is None
    assert override_in_flight(None) is None


def test_the_list_addressed_by_a_name_is_found():
    cfg = OmegaConf.create({"s": {"objects": [{"motion": [{"type": "orbit"}]}], "n": 1}})
    assert list_node(cfg, "s.objects.0.motion.type") == "s.objects.0.motion"
    assert list_node(cfg, "s.objects.type") == "s.objects"
    assert list_node(cfg, "s.objects.0.motion.0.type") is None
    assert list_node(cfg, "s.n") is None and list_node(cfg, "nowhere.x") is None


def test_the_line_names_the_override_the_list_and_the_error():
    assert str(bad_override(ValueError("bad"), "++a.0.b=1", "a.0.b", "a")) == (
        "command line: a.0.b: expected a's items addressed by their index (a is a list), "
        "e.g. a.0.0.b, got ++a.0.b=1 (ValueError: bad)")
    assert str(bad_override(KeyError("k"), "x=1", "x")) == (
        "command line: x: expected a key naming a path of the config, got x=1 (KeyError: 'k')")


@pytest.fixture
def wrapped(monkeypatch):
    """Hydra's override step wrapped for this test only; returns Hydra's own step."""
    original = ConfigLoaderImpl.__dict__["_apply_overrides_to_config"]
    monkeypatch.setattr(ConfigLoaderImpl, "_apply_overrides_to_config", original)
    assert report_bad_overrides() and report_bad_overrides()        # idempotent
    step = ConfigLoaderImpl._apply_overrides_to_config
    assert step._reports_bad_overrides
    assert [c.cell_contents for c in step.__closure__].count(original.__func__) == 1
    return original.__func__


def test_composing_with_a_named_list_item_raises_hydras_compact_error(wrapped):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        with pytest.raises(ConfigCompositionException) as err:
            compose("config", overrides=["scene.objects.0.motion.type=spin"])
        assert str(err.value).startswith(
            "command line: scene.objects.0.motion.type: expected scene.objects.0.motion's "
            "items addressed by their index (scene.objects.0.motion is a list), e.g. "
            "scene.objects.0.motion.0.type, got scene.objects.0.motion.type=spin (ValueError")
        assert isinstance(err.value.__cause__, ValueError)   # HYDRA_FULL_ERROR shows it
        cfg = compose("config", overrides=["scene.objects.0.motion.0.type=spin"])
        assert cfg.scene.objects[0].motion[0].type == "spin"


def test_an_error_outside_the_override_step_is_not_rewritten(wrapped):
    def boom(*args, **kwargs):
        raise ValueError("not an override")

    step = ConfigLoaderImpl._apply_overrides_to_config
    cell = next(c for c in step.__closure__ if c.cell_contents is wrapped)   # Hydra's own
    cell.cell_contents = boom
    with pytest.raises(ValueError, match="not an override"):
        step([], OmegaConf.create({}))
