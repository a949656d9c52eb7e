"""``python -m eventrecon.evaluate run=DIR``: re-renders a finished or interrupted run and
scores it exactly as training did; bad arguments are one line."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest
from integration import tiny_config
from omegaconf import OmegaConf

from eventrecon.data import selection
from eventrecon.engine import build, runner
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


def test_background_only_score_is_what_an_empty_field_renders(run_dir: Path):
    """``psnr_background`` = the PSNR of a zero-density render, computed independently
    (background PNGs vs ground-truth PNGs); the run's own metrics carry it."""
    import numpy as np
    import torch

    from eventrecon.common.colour import srgb_to_linear
    from eventrecon.data.segments import resolve_segments
    from eventrecon.evaluation.heldout import evaluate_heldout, render_heldout
    from eventrecon.fields.base import Field

    cfg = OmegaConf.load(run_dir / ".hydra" / "config.yaml")
    ds = build.load_dataset(cfg)
    heldout, props = selection.heldout_split(ds), build.scene_properties(cfg, ds)
    field, renderer = build.load_segment(cfg, props, run_dir / "seg0")

    class Empty(Field):  # sigma = 0 everywhere
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.zeros(()))

        def forward(self, xyz, t):
            return xyz[:, 0] * 0 * self.w, xyz * 0 + 0.5

    frames = list(range(len(heldout.frame_times)))
    segments = resolve_segments(None)
    empty = render_heldout([(Empty(), renderer)], segments, heldout, [0], frames)
    got = evaluate_heldout(empty, heldout, [0], frames, lpips=False)
    assert got["psnr"] == pytest.approx(got["psnr_background"], abs=1e-9)
    bg = heldout.background[0].astype(np.float64) / 255.0
    gt = heldout.frames[:, 0].astype(np.float64) / 255.0
    ref = np.mean([-10 * np.log10(((bg - g) ** 2).mean()) for g in gt])
    assert got["psnr_background"] == pytest.approx(ref, abs=0.02)  # bg PNG vs 8-bit re-encode
    assert np.allclose(srgb_to_linear(heldout.background[0]), empty[0, 0], atol=1e-6)
    trained = json.loads((run_dir / "metrics.json").read_text())
    assert trained["psnr_background"] == pytest.approx(got["psnr_background"])


def test_colour_corrected_variants_are_separate_and_off_by_default(run_dir: Path):
    assert main([f"run={run_dir}", "color_correct=true"]) == 0
    assert main([f"run={run_dir}", "color_correct=eventnerf"]) == 0
    cc = json.loads((run_dir / "metrics_eval_per_image.json").read_text())
    joint = json.loads((run_dir / "metrics_eval_eventnerf.json").read_text())
    plain = json.loads((run_dir / "metrics_eval.json").read_text())
    assert (cc["color_corrected"], joint["color_corrected"], plain["color_corrected"]) == (
        "per_image", "eventnerf", "none")
    assert len({cc["psnr"], joint["psnr"], plain["psnr"]}) == 3


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


def test_images_render_in_the_precision_the_run_trained_with(run_dir: Path, tmp_path: Path,
                                                             monkeypatch):
    # the record's precision, not what `auto` resolves to on the evaluating machine
    import shutil

    from eventrecon.config import precision

    monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: True)
    for trained, autocast in (("32-true", False), ("bf16-mixed", True)):
        copy = tmp_path / trained
        shutil.copytree(run_dir, copy)
        rec = json.loads((copy / "metrics.json").read_text())
        (copy / "metrics.json").write_text(json.dumps({**rec, "precision": trained}))
        assert main([f"run={copy}"]) == 0
        again = json.loads((copy / "metrics_eval.json").read_text())
        assert (again["precision"], again["image_autocast"]) == (trained, autocast)


@pytest.mark.parametrize("argv,expected", [
    ([], "usage: python -m eventrecon.evaluate run=DIR"),
    (["run=/nowhere"], "/nowhere/.hydra/config.yaml: <file>: expected the run's saved Hydra"),
    (["run=x", "ckpt=first"], "ckpt: expected last or best, got first"),
    (["run=x", "colour=true"], "usage: python -m eventrecon.evaluate"),
    (["run=x", "color_correct=ture"],
     "color_correct: expected one of none, per_image, eventnerf, got ture"),
])
def test_bad_arguments_are_one_line(argv: list[str], expected: str, caplog):
    with caplog.at_level(logging.ERROR):
        assert main(argv) == 2
    (record,) = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert expected in record.getMessage() and "\n" not in record.getMessage()
