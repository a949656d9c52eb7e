"""What TensorBoard shows: every loss term, the learning rate, held-out PSNR on the
curve schedule, the hyperparameters, and images — among them the measured θ·E(t0, t1)
beside the rendered log change of the same window."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from integration import tiny_config

from eventrecon.data.batcher import Segment
from eventrecon.engine import build, runner
from eventrecon.engine.callbacks import HeldOutMonitor
from eventrecon.engine.losses import log_intensity


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("tb")
    cfg = tiny_config(tmp / "data", "logger=tensorboard", "trainer.max_steps=8",
                      "trainer.log_every=2", "trainer.curve_every=4", "trainer.eval_every=8",
                      "trainer.image_every=8")
    runner.run(cfg, tmp / "run")
    return tmp / "run"


def _accumulator(run_dir: Path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    (events,) = run_dir.glob("tb/seg0/events.out.tfevents.*")
    acc = EventAccumulator(str(events), size_guidance={"images": 0, "scalars": 0})
    acc.Reload()
    return acc


def test_scalars_images_and_hyperparameters(run_dir: Path):
    acc = _accumulator(run_dir)
    tags = set(acc.Tags()["scalars"])
    for term in ("loss", "event", "acc", "rgb", "sparsity", "lr", "clip_scale"):
        assert f"train/{term}" in tags, term
    assert [e.step for e in acc.Scalars("val_cheap/psnr")] == [4]  # step 8: the full one
    assert [e.step for e in acc.Scalars("val_full/psnr")] == [8]
    assert acc.Scalars("train/lr")[0].value == pytest.approx(5e-3)
    images = set(acc.Tags()["images"])
    assert {"heldout/render_vs_gt", "heldout/opacity", "heldout/depth",
            "train/events_measured_vs_rendered"} <= images
    hparams = yaml.safe_load((run_dir / "tb" / "seg0" / "hparams.yaml").read_text())
    assert hparams["model.width"] == 48 and hparams["loss.w_rgb"] == 0.01
    assert hparams["trainer.max_steps"] == 8 and "scene.objects" not in hparams


def test_event_image_is_the_measured_and_the_rendered_log_change(tmp_path: Path):
    cfg = tiny_config(tmp_path / "data")
    ds = build.load_dataset(cfg)
    props = build.scene_properties(cfg, ds)
    seg = Segment(0.0, 1000.0)
    module = build.build_module(cfg, props, ds.splits["train"], seg)
    module.last_window = (0.2, 0.7)
    monitor = HeldOutMonitor(ds.splits["validation"], seg, tmp_path, 0, 0, 0, 64, 4096)
    img = monitor._event_image(module)
    b = module.batcher
    H, W = b.cameras.height, b.cameras.width
    assert img.shape == (H, 2 * W, 3) and np.abs(img).max() <= 1.0 + 1e-6
    signed = img[..., 0] - img[..., 2]  # red = brighter, blue = darker, common scale
    theta_e = props.threshold * b.events.window_all(200.0, 700.0)[0].numpy()
    scale = np.abs(theta_e).max() / max(np.abs(signed[:, :W]).max(), 1e-12)
    np.testing.assert_allclose(signed[:, :W] * scale, theta_e, atol=1e-5)
    with torch.no_grad():
        rgbs = [module.renderer.render_image(module.field, b.cameras, 0, t, b.background[0])["rgb"]
                for t in (0.2, 0.7)]
    mask = torch.as_tensor(np.eye(3)[(np.arange(H)[:, None] % 2) + (np.arange(W) % 2)],
                           dtype=torch.float32)  # RGGB: channel = row%2 + col%2
    seen = [(r * mask).sum(-1) for r in rgbs]
    change = (log_intensity(seen[1], props.tonemap_eps)
              - log_intensity(seen[0], props.tonemap_eps)).numpy()
    np.testing.assert_allclose(signed[:, W:] * scale, change, atol=1e-4)
