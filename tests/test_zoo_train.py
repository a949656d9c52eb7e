"""`python train.py model=X` trains every backbone through the same module and renderer."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from integration import TINY, tiny_config

from eventrecon.data.segments import resolve_segments
from eventrecon.engine import build, runner

SMALL = {
    "ngp": ["model.log2_table_size=14", "model.anneal_steps=10"],
    "tensorf_cp": [],
    "hexplane": [],
}


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("data")


@pytest.mark.parametrize("model", sorted(SMALL))
def test_backbone_trains_and_reports_metrics(model: str, data_dir: Path, tmp_path: Path):
    cfg = tiny_config(data_dir, f"model={model}", "trainer.max_steps=30", *SMALL[model],
                      base=TINY)
    metrics = runner.run(cfg, tmp_path)
    # 30 steps may leave a backbone at its initial fog or at the empty field: the status is
    # then judged by the collapse rule (within 0.05 dB of the empty field), never "failed"
    assert metrics["model"] == model and metrics["status"] in ("ok", "collapsed")
    assert (metrics["status"] == "collapsed") == (abs(metrics["gain_psnr"]) < 0.05)
    assert metrics["steps"] == 30 and metrics["nonfinite_steps"] == 0
    assert math.isfinite(metrics["psnr"]) and 0 < metrics["ssim"] <= 1
    assert metrics["psnr"] > 10.0  # a render, not noise or NaN


def test_ngp_cylinder_annealing_reaches_full_radius_with_finite_losses(data_dir: Path,
                                                                       tmp_path: Path):
    import torch

    from eventrecon.engine.losses import total_loss
    from eventrecon.engine.module import step_generator

    cfg = tiny_config(data_dir, "model=ngp", "trainer.max_steps=24", *SMALL["ngp"], base=TINY)
    ds = build.load_dataset(cfg)
    module, _ = runner.train_segment(cfg, build.scene_properties(cfg, ds), ds.splits["train"],
                                     None, 0,
                                     resolve_segments(None)[0], tmp_path)
    assert module.nonfinite_total == 0
    assert module.renderer.clip_scale == pytest.approx(1.0)
    # the schedule: 0 at the start, linear over its steps (the paper: 1e4 of them)
    from baselines.schedules import CylinderAnneal

    cb = [c for c in module.field.callbacks() if isinstance(c, CylinderAnneal)][0]
    assert cb.steps == 10 and cb.scale(5) == pytest.approx(0.5)
    assert tiny_config(data_dir, "model=ngp", base=TINY).model.anneal_steps == 10000
    batch = module.batcher.sample(64, step_generator(5, 5))
    terms = total_loss(module.render_three(batch, None, perturb=False), batch, module.loss_cfg, 24)
    assert all(torch.isfinite(v) for v in terms.values())
