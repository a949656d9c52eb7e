"""Collapsed runs are never results: detected, recorded, reported; and the faithful
defaults keep the collapse-prone rows alive."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from integration import TINY, tiny_config

from eventrecon.engine import runner
from eventrecon.engine.collapse import CollapseRule, collapse_reason, opacity_collapsed
from eventrecon.report import build_report


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("data")


def test_rule_needs_the_whole_final_stretch_below_the_floor():
    rule = CollapseRule(opacity_floor=1e-3, window=0.25)
    log = [(s, 0.3) for s in range(25, 775, 25)] + [(s, 1e-5) for s in range(775, 1025, 25)]
    assert opacity_collapsed(log, rule)  # the last 10 of 40 points are below the floor
    log[-3] = (950, 0.2)  # one live point in the final quarter: not collapsed
    assert not opacity_collapsed(log, rule)
    assert collapse_reason([log], 23.0, 21.0, rule) is None
    assert "within 0.05 dB" in collapse_reason([log], 21.04, 21.0, rule)


def test_the_psnr_rule_also_asks_the_subject_when_the_run_has_one():
    rule, live = CollapseRule(), [[(25, 0.2)]]
    # rig_drift full seed 0: full frame 0.004 dB from the empty field, subject +1.21 dB
    assert collapse_reason(live, 22.067, 22.063, rule, 16.88, 15.67) is None
    # the subject at the empty field too: an empty render
    assert "within 0.05 dB" in collapse_reason(live, 22.067, 22.063, rule, 15.70, 15.67)
    # no subject figures (no masks): the full frame decides alone, as before
    assert "within 0.05 dB" in collapse_reason(live, 22.067, 22.063, rule, None, 15.67)
    assert "within 0.05 dB" in collapse_reason(live, 22.067, 22.063, rule, float("nan"), 15.67)
    # a subject at the empty field alone is no collapse when the full frame is not
    assert collapse_reason(live, 23.0, 22.063, rule, 15.70, 15.67) is None


def test_a_forced_collapse_is_reported_as_collapsed(data_dir: Path, tmp_path: Path):
    """A field whose density is driven to zero (softplus(raw − 30)) renders the empty scene:
    status collapsed in metrics.json, "collapsed" in the tables, never a score."""
    cfg = tiny_config(data_dir, "trainer.max_steps=20", "trainer.log_every=2",
                      "model.density_shift=-30", "experiment=table3")
    metrics = runner.run(cfg, tmp_path / "run")
    assert metrics["status"] == "collapsed"
    assert metrics["psnr"] == pytest.approx(metrics["psnr_background"], abs=1e-6)
    assert "mean opacity below" in metrics["collapse_reason"]
    saved = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert saved["status"] == "collapsed" and saved["collapse_reason"]
    build_report([tmp_path / "run"], tmp_path / "report", tables=["table3"])
    text = (tmp_path / "report" / "table3.md").read_text()
    row = next(ln for ln in text.splitlines() if ln.startswith("| Full Model")
               and "collapsed" in ln)
    assert "0/1 (1 collapsed)" in row and f"{metrics['psnr']:.3f}" not in row


def test_no_acc_keeps_its_density_with_the_faithful_defaults(data_dir: Path, tmp_path: Path):
    """The CPU-size NeRF with the authors' initialisation and absolute sparsity ramp (and
    the CPU sizing's betas^10): without L_acc the field keeps rendering something (the
    ramp compressed to the run made L_sparsity ~100× stronger per step and collapsed this
    row)."""
    cfg = tiny_config(data_dir, "loss=no_acc", "trainer.max_steps=120", "trainer.log_every=10",
                      "trainer.schedule=compressed", base=TINY)
    assert cfg.model.optim.lr == 1e-3 and cfg.loss.sparsity_ramp == 30000  # the CPU size
    metrics = runner.run(cfg, tmp_path)
    done = json.loads((tmp_path / "seg0" / "done.json").read_text())
    opacities = [o for _, o in done["opacity_log"]]
    assert metrics["status"] == "ok" and min(opacities) > 1e-3, opacities
