"""``python -m eventrecon.evaluate run=DIR``: re-renders a finished or interrupted run and
scores it exactly as training did; bad arguments are one line."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest
from integration import tiny_config
from omegaconf import OmegaConf

from eventrecon import runner
from eventrecon.evaluate import main


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("eval")
    cfg = tiny_config(tmp / "data", "trainer.max_steps=6", "data.eval_every_frames=1",
                      "+scene.segments=[[0,510],[490,1000]]")
    run = tmp / "run"
    runner.run(cfg, run)
    (run / ".hydra").mkdir()
    OmegaConf.save(cfg, run / ".hydra" / "config.yaml")  # what Hydra saves for a run
    return run


def test_reevaluation_equals_the_runs_own_metrics(run_dir: Path):
    assert main([f"run={run_dir}"]) == 0
    trained = json.loads((run_dir / "metrics.json").read_text())
    again = json.loads((run_dir / "metrics_eval.json").read_text())
    assert again["checkpoint"] == "last" and again["n_frames"] == trained["n_frames"] == 11
    assert again["psnr"] == trained["psnr"] and again["ssim"] == trained["ssim"]
    pngs = sorted((run_dir / "eval_last" / "renders").rglob("*.png"))
    assert len(pngs) == 11 and (run_dir / "eval_last" / "renders" / "06.gif").stat().st_size > 1000


def test_colour_corrected_variant_is_separate_and_off_by_default(run_dir: Path):
    assert main([f"run={run_dir}", "color_correct=true"]) == 0
    cc = json.loads((run_dir / "metrics_eval_cc.json").read_text())
    plain = json.loads((run_dir / "metrics_eval.json").read_text())
    assert cc["color_corrected"] is True and plain["color_corrected"] is False
    assert cc["psnr"] != plain["psnr"]


def test_an_interrupted_run_evaluates_from_its_last_checkpoints(run_dir: Path, tmp_path: Path):
    import shutil

    cut = tmp_path / "cut"
    shutil.copytree(run_dir, cut)
    for done in cut.glob("seg*/done.json"):
        done.unlink()  # as if killed before finishing: only checkpoints remain
    (cut / "metrics.json").unlink()
    assert main([f"run={cut}"]) == 0
    again = json.loads((cut / "metrics_eval.json").read_text())
    assert again["psnr"] == json.loads((run_dir / "metrics_eval.json").read_text())["psnr"]


@pytest.mark.parametrize("argv,expected", [
    ([], "usage: python -m eventrecon.evaluate run=DIR"),
    (["run=/nowhere"], "/nowhere/.hydra/config.yaml: <file>: expected the run's saved Hydra"),
    (["run=x", "ckpt=first"], "ckpt: expected last or best, got first"),
    (["run=x", "colour=true"], "usage: python -m eventrecon.evaluate"),
])
def test_bad_arguments_are_one_line(argv: list[str], expected: str, caplog):
    with caplog.at_level(logging.ERROR):
        assert main(argv) == 2
    (record,) = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert expected in record.getMessage() and "\n" not in record.getMessage()
