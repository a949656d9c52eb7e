"""Where a scene's ε, θ, decay, Bayer flag, duration and segments come from:
explicit ``data.X`` > the dataset's ``meta.json`` > the preset's ``data.fallback`` > error."""

from __future__ import annotations

import pytest
from integration import tiny_config

from eventrecon.common.errors import InputError
from eventrecon.data.properties import resolve_properties

REAL = {"tonemap_eps": 0.03, "decay": 0.93, "bayer": True,
        "segments": [[0, 210], [190, 410], [390, 610], [590, 810], [790, 1000]]}


def test_precedence_explicit_then_meta_then_fallback():
    meta = {"tonemap_eps": 0.02, "bayer": False}  # e.g. converted with --no-bayer
    p = resolve_properties({"decay": 0.5, "fallback": REAL}, meta, "scene")
    assert (p.decay, p.tonemap_eps, p.bayer) == (0.5, 0.02, False)  # config, meta, meta
    assert p.segments == [[float(a), float(b)] for a, b in REAL["segments"]]  # fallback
    assert (p.threshold, p.duration_s, p.cylinder["radius"]) == (0.5, None, 0.5)  # defaults


def test_missing_properties_name_the_keys_and_the_presets():
    with pytest.raises(InputError, match=r"^scene/meta\.json: tonemap_eps, decay, bayer: "
                                         r"expected .*data=real.*data=synthetic.*got missing$"):
        resolve_properties({}, {}, "scene")


@pytest.mark.parametrize("source,key,value,expect", [
    ("config", "decay", 1.5, r"config data\.decay: decay: expected a decay b in \(0, 1\]"),
    ("meta", "tonemap_eps", 0.0, r"scene/meta\.json: tonemap_eps: expected a number > 0"),
    ("meta", "bayer", "yes", r"meta\.json: bayer: expected true or false, got yes"),
    ("config", "segments", [[10, 5]], r"data\.segments: segments: expected a list of \[start"),
])
def test_out_of_range_values_are_one_line(source, key, value, expect):
    base = {"tonemap_eps": 0.01, "decay": 1.0, "bayer": False}
    overrides, meta = ({key: value}, base) if source == "config" else ({}, {**base, key: value})
    with pytest.raises(InputError, match=expect):
        resolve_properties(overrides, meta, "scene")


def test_presets_compose_into_fallback(tmp_path):
    real = tiny_config(tmp_path, "data=real").data
    assert real.fallback.decay == 0.93 and real.decay is None  # meta.json still wins
    synthetic = tiny_config(tmp_path, "data=synthetic").data
    assert synthetic.fallback.tonemap_eps == 0.01 and synthetic.fallback.segments == [[0, 1000]]
