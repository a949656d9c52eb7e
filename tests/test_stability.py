"""Mixed precision and the non-finite guard, through the real module and a real Lightning fit.

- bf16: one training step (``render_three`` + ``total_loss`` + backward + AdamW) under CPU
  bf16 autocast is finite for every backbone, autocast really runs ops in bf16, and the
  loss and gradient agree with the fp32 step (relative loss error < 1e-2, gradient
  cosine > 0.99).
- Guard: NaN is injected into the loss at chosen steps (``total_loss`` wrapped); skipped
  steps leave the parameters bit-identical, the counter reaches TensorBoard, intermittent
  NaNs let the run finish with finite metrics, ``max_nonfinite`` in a row stop it with one
  line and ``nonfinite-stop.ckpt``; a diverging run (lr = 1e30) stops ``train.py`` with
  exit status 3.
"""

from __future__ import annotations

import logging
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from integration import TINY, TINY_NERF, tiny_config
from torch.utils._python_dispatch import TorchDispatchMode

import eventrecon.engine.module as module_lib
from eventrecon.data.segments import resolve_segments
from eventrecon.engine import build, runner
from eventrecon.engine.losses import total_loss
from eventrecon.engine.module import EventNeRFModule, NonFiniteLossError, step_generator
from eventrecon.sim.pipeline import ensure_dataset

ROOT = Path(__file__).resolve().parents[1]
BACKBONES = {
    "nerf": TINY_NERF,
    "ngp": ["model.log2_table_size=14"],
    "tensorf_cp": [],
    "hexplane": [],
}


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("data")


class _Bf16Ops(TorchDispatchMode):
    """Records the aten ops that produced a bf16 tensor (proves autocast engaged)."""

    def __init__(self) -> None:
        super().__init__()
        self.ops: set[str] = set()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        if isinstance(out, torch.Tensor) and out.dtype == torch.bfloat16:
            self.ops.add(str(func))
        return out


def _module(data_dir: Path, model: str) -> EventNeRFModule:
    cfg = tiny_config(data_dir, f"model={model}", *BACKBONES[model], base=TINY)
    ds = build.load_dataset(cfg)
    props = build.scene_properties(cfg, ds)
    seg = resolve_segments(props.segments)[0]
    torch.manual_seed(0)
    return build.build_module(cfg, props, ds.splits["train"], seg)


def _step(mod: EventNeRFModule, batch: dict, bf16: bool) -> tuple[torch.Tensor, torch.Tensor, set]:
    """Loss and flat gradient of one step; the set of ops that ran in bf16."""
    mod.field.zero_grad(set_to_none=True)
    spy = _Bf16Ops()
    with spy, torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
        levels = mod.render_three(batch, step_generator(0, 1, 1))
        loss = total_loss(levels, batch, mod.loss_cfg, 1)["loss"]
        reg = mod.field.regularization()
        if reg is not None:
            loss = loss + reg
    loss.backward()
    grads = [p.grad for p in mod.field.parameters()]
    assert all(g is not None for g in grads), "every parameter receives a gradient"
    return loss.detach(), torch.cat([g.flatten().float() for g in grads]), spy.ops


@pytest.mark.parametrize("model", sorted(BACKBONES))
def test_bf16_training_step_is_finite_and_matches_fp32(model: str, data_dir: Path):
    mod = _module(data_dir, model)
    batch = mod.batcher.sample(96, step_generator(0, 1))
    loss32, g32, _ = _step(mod, batch, bf16=False)
    loss16, g16, ops = _step(mod, batch, bf16=True)
    # the MLPs' linear layers really ran in bf16 (NGP's are bias-free: mm); the factorised
    # backbones have no layer autocast lowers (grid_sample and products stay float32)
    expected = {"nerf": {"aten.addmm.default"}, "ngp": {"aten.mm.default"}}.get(model, set())
    assert expected <= ops and (ops or model not in ("nerf", "ngp"))
    assert loss16.dtype == torch.float32 and bool(torch.isfinite(loss16))
    assert bool(torch.isfinite(g16).all())
    assert abs(float(loss16 - loss32)) < 1e-2 * float(loss32)
    # NGP's bias-free decoder on 1e-4 features loses more to bf16 (measured cosine 0.9865)
    bound = 0.98 if model == "ngp" else 0.99
    assert float(torch.nn.functional.cosine_similarity(g16, g32, dim=0)) > bound
    opt = mod.configure_optimizers()
    before = [p.detach().clone() for p in mod.field.parameters()]
    opt.step()
    after = list(mod.field.parameters())
    assert all(bool(torch.isfinite(p).all()) for p in after)
    assert any(not torch.equal(a, b) for a, b in zip(after, before))


# ------------------------------------------------------------------ the non-finite guard
def _inject_nan(monkeypatch, bad_steps: set[int], losses: dict[int, float] | None = None
                ) -> dict[int, dict[str, torch.Tensor]]:
    """NaN in L_event at ``bad_steps``; returns the field parameters seen at each step
    (and fills ``losses`` with each step's finite total loss)."""
    real = module_lib.total_loss

    def nan_at_bad_steps(levels, batch, cfg, step):
        terms = real(levels, batch, cfg, step)
        if losses is not None:
            losses[step] = float(terms["loss"])
        if step in bad_steps:
            terms["event"] = terms["event"] * float("nan")
            terms["loss"] = terms["loss"] + terms["event"]
        return terms

    seen: dict[int, dict[str, torch.Tensor]] = {}
    step_fn = EventNeRFModule.training_step

    def spy(self, batch, batch_idx):
        seen[int(self.global_step)] = {n: p.detach().clone()
                                       for n, p in self.field.named_parameters()}
        return step_fn(self, batch, batch_idx)

    monkeypatch.setattr(module_lib, "total_loss", nan_at_bad_steps)
    monkeypatch.setattr(EventNeRFModule, "training_step", spy)
    return seen


def _same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def _tensorboard_scalar(run_dir: Path, tag: str) -> list[tuple[int, float]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    (events,) = run_dir.glob("tb/seg0/events.out.tfevents.*")
    acc = EventAccumulator(str(events))
    acc.Reload()
    return [(e.step, e.value) for e in acc.Scalars(tag)]


def test_intermittent_nonfinite_steps_are_skipped_and_counted(monkeypatch, caplog, data_dir: Path,
                                                              tmp_path: Path):
    bad = {3, 4, 9}  # never 3 in a row
    losses: dict[int, float] = {}
    seen = _inject_nan(monkeypatch, bad, losses)
    cfg = tiny_config(data_dir, "trainer.max_steps=12", "trainer.max_nonfinite=3",
                      "trainer.log_every=4", "logger=tensorboard")
    with caplog.at_level(logging.WARNING, logger="eventrecon.engine.module"):
        metrics = runner.run(cfg, tmp_path)
    assert metrics["status"] in ("ok", "collapsed") and metrics["steps"] == 12
    assert metrics["nonfinite_steps"] == 3
    assert math.isfinite(metrics["psnr"]) and metrics["psnr"] > 10.0
    assert 0 < metrics["ssim"] <= 1
    # a skipped step leaves every parameter bit-identical; a normal step changes them
    assert sorted(seen) == list(range(12))
    for s in range(11):
        assert _same(seen[s], seen[s + 1]) == (s in bad), s
    warnings = [r.getMessage() for r in caplog.records if "non-finite loss" in r.getMessage()]
    assert len(warnings) == 3 and all("(event, loss); step skipped" in w for w in warnings)
    assert "step 4: " in warnings[1] and "(2 in a row)" in warnings[1]
    assert "(1 in a row)" in warnings[2]  # step 9: the streak was reset by good steps
    # TensorBoard (written every 4th step: 3, 7, 11) has the running count of skipped
    # steps, and each logged loss is the loss of the step it is filed under
    assert _tensorboard_scalar(tmp_path, "train/nonfinite_steps") == [(3, 1.0), (7, 2.0),
                                                                      (11, 3.0)]
    logged = _tensorboard_scalar(tmp_path, "train/loss")
    assert [s for s, _ in logged] == [7, 11]
    for s, v in logged:
        assert v == pytest.approx(losses[s], rel=1e-6)


def test_nonfinite_losses_in_a_row_stop_with_checkpoint(monkeypatch, data_dir: Path,
                                                        tmp_path: Path):
    seen = _inject_nan(monkeypatch, {5, 6, 7})
    cfg = tiny_config(data_dir, "trainer.max_steps=20", "trainer.max_nonfinite=3")
    with pytest.raises(NonFiniteLossError) as err:
        runner.run(cfg, tmp_path)
    msg = str(err.value)
    ckpt = tmp_path / "seg0" / "checkpoints" / "nonfinite-stop.ckpt"
    assert "\n" not in msg
    assert msg == (f"3 non-finite losses in a row at step 7 (event, loss); stopped, "
                   f"checkpoint {ckpt}")
    assert max(seen) == 7 and not (tmp_path / "metrics.json").exists()
    state = torch.load(ckpt, map_location="cpu", weights_only=False)
    assert state["eventrecon"]["nonfinite_total"] == 3
    field = {k[len("field."):]: v for k, v in state["state_dict"].items()
             if k[len("field."):] in seen[5]}
    assert all(bool(torch.isfinite(v).all()) for v in field.values())
    # the saved model is the last good one: the parameters after step 4
    assert _same(field, seen[5]) and _same(seen[5], seen[7])


def test_diverging_run_stops_train_py_with_one_line(data_dir: Path, tmp_path: Path):
    """lr = 1e30 blows the MLP up after one step: the guard, not a NaN model, ends the run."""
    ensure_dataset(tiny_config(data_dir).scene, data_dir)
    run_dir = tmp_path / "run"
    cmd = [sys.executable, str(ROOT / "train.py"), *TINY, *TINY_NERF, f"data_dir={data_dir}",
           "trainer.max_steps=20", "trainer.max_nonfinite=3", "model.optim.lr=1e30",
           "evaluate=false", f"hydra.run.dir={run_dir}"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "EVENTRECON_OFFLINE": "1"}
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 3, out[-2000:]
    assert "Traceback" not in out
    errors = [ln for ln in out.splitlines() if "[ERROR]" in ln]
    assert len(errors) == 1 and "non-finite losses in a row" in errors[0]
    assert (run_dir / "seg0" / "checkpoints" / "nonfinite-stop.ckpt").is_file()
    assert not (run_dir / "metrics.json").exists()


@pytest.mark.parametrize("native, expected", [(True, "bf16-mixed"), (False, "32-true")])
def test_auto_precision_takes_bf16_only_on_a_cpu_with_native_bf16(
        tmp_path: Path, monkeypatch, native: bool, expected: str):
    import eventrecon.config.precision as precision
    from eventrecon.results import records

    monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: native)
    cfg = tiny_config(tmp_path)
    assert cfg.trainer.lightning.precision == "auto"            # the default at trainer=cpu
    trainer = runner._trainer(cfg, tmp_path / "seg0", [], 0)
    assert trainer.precision == expected
    assert records.run_info(cfg, {})["precision"] == expected    # the record names it
    written = tiny_config(tmp_path, "trainer.lightning.precision=bf16-mixed")
    assert runner._trainer(written, tmp_path / "seg1", [], 0).precision == "bf16-mixed"


@pytest.mark.parametrize("model", ["ngp", "hexplane", "tensorf_cp"])
def test_auto_precision_keeps_the_grid_backbones_in_fp32(tmp_path: Path, monkeypatch,
                                                         model: str):
    """bf16 autocast does not speed their steps (``model.cpu_bf16: false``), so ``auto``
    trains them in fp32 even where the CPU has native bf16; a written value still wins."""
    import eventrecon.config.precision as precision
    from eventrecon.results import records

    monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: True)
    cfg = tiny_config(tmp_path, f"model={model}", base=TINY)
    assert cfg.model.cpu_bf16 is False
    assert runner._trainer(cfg, tmp_path / "seg0", [], 0).precision == "32-true"
    assert records.run_info(cfg, {})["precision"] == "32-true"
    written = tiny_config(tmp_path, f"model={model}", "trainer.lightning.precision=bf16-mixed",
                          base=TINY)
    assert runner._trainer(written, tmp_path / "seg1", [], 0).precision == "bf16-mixed"
