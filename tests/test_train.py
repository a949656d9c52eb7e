"""The method end to end on a tiny simulated scene: the loss goes down, the held-out
render beats a constant colour, segments cross-fade, TensorBoard and checkpoints appear."""

from __future__ import annotations

import copy
import json
import math
import os
import shutil
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from integration import tiny_config

from eventrecon.common.errors import InputError
from eventrecon.data import selection
from eventrecon.data.batcher import Segment
from eventrecon.engine import build, runner
from eventrecon.engine.losses import total_loss
from eventrecon.engine.module import step_generator
from eventrecon.engine.segments import segment_config, segment_steps
from eventrecon.results import records
from eventrecon.results.machine import machine_name
from eventrecon.results.records import stitch_curves
from eventrecon.sim.pipeline import dataset_path


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("data")


def _fixed_batch_loss(module, steps=range(10_000, 10_004)) -> dict[str, float]:
    """Mean loss terms on fixed batches, no stratified jitter (same batches each call)."""
    vals: dict[str, list[float]] = {"loss": [], "rgb": []}
    with torch.no_grad():
        for s in steps:
            g = step_generator(123, s)
            batch = module.batcher.sample(96, g)
            levels = module.render_three(batch, None, perturb=False)
            terms = total_loss(levels, batch, module.loss_cfg, 10_000)
            for k in vals:
                vals[k].append(float(terms[k]))
    return {k: float(np.mean(v)) for k, v in vals.items()}


def test_200_steps_lower_the_loss_and_beat_a_constant_colour(data_dir: Path, tmp_path: Path):
    # blocks: textured boxes large enough at 32x24 px to be learnt in 200 steps (measured:
    # +1.7..2.1 dB over the constant colour for seeds 0, 1, 3, 4; the small spheres need
    # ~1000 steps at this size before they beat the grey background reliably)
    # fp32 on every machine: under bf16 autocast (precision auto on a CPU with native
    # bf16) the trajectory is another one per CPU, and its RGB term after 200 steps
    # ranged 0.69-0.92 of the start over seeds 0, 2, 4 and two commits (session 45)
    cfg = tiny_config(data_dir, "scene=blocks", "trainer.max_steps=200",
                      "trainer.checkpoint_every=100", "trainer.lightning.precision=32-true")
    metrics = runner.run(cfg, tmp_path)
    # the loss before training, with the same initial field (same seed as the run)
    ds = build.load_dataset(cfg)
    train = ds.splits["train"]
    L.seed_everything(cfg.seed, verbose=False)
    fresh = build.build_module(cfg, build.scene_properties(cfg, ds), train, Segment(0, 1000))
    trained_sd = torch.load(tmp_path / "seg0" / "checkpoints" / "last.ckpt",
                            weights_only=False)["state_dict"]
    before = _fixed_batch_loss(fresh)
    fresh.load_state_dict(trained_sd, strict=False)
    after = _fixed_batch_loss(fresh)
    # measured (fp32; the authors' N(0,1) density bias starts as a fog that L_sparsity and
    # L_acc clear): method version 3, total 0.2245 -> 0.2030 (-9.6 %), RGB term 0.0115 ->
    # 0.0091, held-out 26.78 dB; version 2 started higher, 0.266 -> 0.229 (-13.8 %), RGB
    # 0.0131 -> 0.0106, 25.86 dB. (Seeds 1 and 3 collapse to the empty field in both.)
    # Version 4 on a Zen 4 EPYC (session 45): total x0.906, RGB x0.773, 26.77 dB.
    assert after["loss"] < 0.93 * before["loss"], (before, after)
    assert after["rgb"] < 0.85 * before["rgb"], (before, after)

    # held-out PSNR beats the best constant colour (the mean GT colour) on the same frames
    val = ds.splits["validation"]
    frames = list(range(0, len(val.frame_times), 5))
    gt = val.frames[frames].astype(np.float64) / 255
    const = gt.reshape(-1, 3).mean(0)
    const_psnr = -10 * math.log10(float(np.mean((gt - const) ** 2)))
    assert metrics["psnr"] > const_psnr + 1.0, (metrics["psnr"], const_psnr)
    assert metrics["steps"] == 200 and metrics["status"] == "ok"
    saved = json.loads((tmp_path / "metrics.json").read_text())
    assert saved["psnr"] == pytest.approx(metrics["psnr"])
    assert saved["machine"] == machine_name() and saved["machine"].endswith(f"×{os.cpu_count()}")
    assert (tmp_path / "renders" / f"{val.cameras.names[0]}.gif").stat().st_size > 0


def test_one_parameter_set_for_coarse_and_fine(data_dir: Path, tmp_path: Path):
    cfg = tiny_config(data_dir, "trainer.max_steps=1")
    ds = build.load_dataset(cfg)
    m = build.build_module(cfg, build.scene_properties(cfg, ds), ds.splits["train"],
                            Segment(0, 1000))
    field = m.field
    assert sum(p.numel() for p in m.renderer.parameters()) == 0
    levels = m.render_three(m.batcher.sample(32, step_generator(0, 0)), step_generator(0, 0))
    assert len(levels) == 2
    grads = []
    for lv in levels:
        field.zero_grad()
        lv["rgb_t1"].sum().backward(retain_graph=True)
        grads.append([p.grad is not None and bool(p.grad.abs().sum() > 0)
                      for p in field.parameters()])
    assert all(grads[0]) and all(grads[1])  # both levels reach every parameter of ONE field
    opt = m.configure_optimizers()
    in_optimiser = {id(p) for g in opt.param_groups for p in g["params"]}
    assert in_optimiser == {id(p) for p in field.parameters()}


def test_each_view_draws_its_own_reference_frame_and_its_rays_agree_with_it(data_dir: Path):
    """The authors draw the reference frame per view: within a view every ray has the same
    ``t_ref``, its frame's colour and ``V(t1) − V(t_ref)``; across steps views differ."""
    cfg = tiny_config(data_dir, "trainer.max_steps=1")
    ds = build.load_dataset(cfg)
    m = build.build_module(cfg, build.scene_properties(cfg, ds), ds.splits["train"],
                           Segment(0, 1000))
    b = m.batcher
    H, W = b.cameras.height, b.cameras.width
    mixed = 0
    for step in range(12):
        batch = b.sample(64, step_generator(7, step))
        view, row, col = batch["view"], batch["row"], batch["col"]
        t1 = b.segment.units(b.last_window[1])          # the window's own end, float64
        per_view = []
        for v in view.unique().tolist():
            t_ref = batch["t_ref"][view == v, 0]
            assert bool((t_ref == t_ref[0]).all())
            per_view.append(float(t_ref[0]))
        mixed += len(set(per_view)) > 1
        t_ref_u = b.segment.units(batch["t_ref"][:, 0].double())
        ref = (b.frame_times[None, :] - t_ref_u[:, None]).abs().argmin(1)
        # the frame is one of the two nearest t1
        near2 = (b.frame_times - float(t1)).abs().argsort(stable=True)[:2]
        assert bool(torch.isin(ref, near2).all())
        assert torch.equal(batch["ref_rgb"], b.frames[ref, view, row, col])
        pix = (view * H + row) * W + col
        want = b.events.window(pix, b.frame_times[ref].double(),
                               torch.full_like(t_ref_u, float(t1)))
        torch.testing.assert_close(batch["events_ref"], want.float())
    assert mixed >= 3   # P(all views agree) is 2^(1-V) per step when two frames qualify


def test_multisegment_run_trains_each_segment_and_crossfades(data_dir: Path, tmp_path: Path):
    cfg = tiny_config(data_dir, "trainer.max_steps=4", "+scene.segments=[[0,510],[490,1000]]")
    metrics = runner.run(cfg, tmp_path)
    assert metrics["segments"] == [[0.0, 510.0], [490.0, 1000.0]]
    assert metrics["steps"] == 8
    for k in (0, 1):
        assert (tmp_path / f"seg{k}" / "checkpoints" / "last.ckpt").exists()
    no_multi = runner.run(tiny_config(data_dir, "trainer.max_steps=4", "loss=no_multiseg",
                                      "+scene.segments=[[0,510],[490,1000]]"), tmp_path / "b")
    assert no_multi["segments"] == [[0.0, 1000.0]]


def test_segments_trained_by_separate_jobs_equal_one_run(data_dir: Path, tmp_path: Path):
    """``-m data.segment=0,1``: jobs share the run folder; the first reports 'partial', the
    one completing the set evaluates — with exactly the metrics of one run training both."""
    seg = ["trainer.max_steps=4", "+scene.segments=[[0,510],[490,1000]]"]
    whole = runner.run(tiny_config(data_dir, *seg), tmp_path / "whole")
    first = runner.run(tiny_config(data_dir, *seg, "data.segment=0"), tmp_path / "jobs")
    assert first["status"] == "partial" and first["missing_segments"] == [1]
    assert not (tmp_path / "jobs" / "metrics.json").exists()
    second = runner.run(tiny_config(data_dir, *seg, "data.segment=1"), tmp_path / "jobs")
    # (4 steps a segment: the status may be "collapsed"; it must be the one-run status)
    assert second["status"] == whole["status"] != "partial"
    assert second["steps"] == whole["steps"] == 8
    for key in ("psnr", "ssim"):
        assert second[key] == whole[key], key  # segment 0 loaded from its checkpoint
    with pytest.raises(InputError, match=r"data\.segment: expected a segment index in \[0, 1\]"):
        runner.run(tiny_config(data_dir, *seg, "data.segment=2"), tmp_path / "bad")


def test_views_and_fps_selection(data_dir: Path):
    cfg = tiny_config(data_dir)
    ds = build.load_dataset(cfg)
    train = ds.splits["train"]
    three = selection.select_views(train, 3)
    assert three.cameras.names == [train.cameras.names[i] for i in (0, 2, 4)]
    assert len(three.events) == 3 and three.frames.shape[1] == 3
    one = selection.select_fps(train, 0.5, float(ds.meta["duration_s"]))
    assert one.frame_times.tolist() == [0.0]
    from eventrecon.common.errors import InputError
    with pytest.raises(InputError, match="data.fps"):
        selection.select_fps(train, 1000.0, float(ds.meta["duration_s"]))
    with pytest.raises(InputError, match="data.views"):
        selection.select_views(train, 7)


def test_select_fps_tolerates_rounded_frame_names_and_one_frame(data_dir: Path):
    from dataclasses import replace

    train = build.load_dataset(tiny_config(data_dir)).splits["train"]
    # frame folders named to 1e-4 units: a 3.7 s clip at 5 FPS (step 54.054...)
    times = np.round(np.arange(len(train.frame_times)) * 1000 / 18.5, 4)
    odd = replace(train, frame_times=times)
    assert len(selection.select_fps(odd, 5.0, 3.7).frame_times) == len(times)  # all kept
    one = replace(train, frame_times=times[:1], frames=train.frames[:1])
    assert selection.select_fps(one, 100.0, 3.7).frame_times.tolist() == [0.0]


def test_compressed_schedules_follow_each_segments_own_length(data_dir: Path):
    """A split budget (trainer.split_steps) with compressed schedules: each segment's
    warm-up is its own share of the paper's run; paper schedules stay in steps."""
    cfg = tiny_config(data_dir, "trainer.max_steps=15000", "trainer.split_steps=true",
                      "trainer.schedule=compressed", "model.anneal_steps=${paper_steps:4000}")
    steps = segment_steps(cfg, 5)
    seg = segment_config(cfg, steps)
    assert steps == 3000 and seg.trainer.max_steps == 3000 and not seg.trainer.split_steps
    assert seg.model.anneal_steps == 80  # 4000 · 3000 / 150000, of the segment, not the run
    paper = segment_config(tiny_config(data_dir, "trainer.max_steps=15000",
                                       "trainer.split_steps=true",
                                       "model.anneal_steps=${paper_steps:4000}"), 3000)
    assert paper.model.anneal_steps == 4000
    assert segment_config(tiny_config(data_dir), 10) is not None


def test_stitched_curves_make_steps_and_wall_clock_cumulative(tmp_path: Path):
    for k, (rows, steps, wall) in enumerate([([(1.0, 5), (2.0, 10)], 10, 2.5),
                                             ([(0.5, 5), (3.0, 10)], 10, 3.0)]):
        d = tmp_path / f"seg{k}"
        d.mkdir()
        (d / "curve.csv").write_text("wall_s,step,psnr,ssim,lpips,kind\n" + "".join(
            f"{w},{s},20,,,cheap\n" for w, s in rows))
        (d / "done.json").write_text(json.dumps({"steps": steps, "wall_s": wall}))
    rows = stitch_curves([tmp_path / "seg0", tmp_path / "seg1"])
    assert [(r["wall_s"], r["step"]) for r in rows] == [
        ("1.000", "5"), ("2.000", "10"), ("3.000", "15"), ("5.500", "20")]
    # the report reads a run without a top-level curve.csv the same way
    from eventrecon.report.runs import read_curve

    cols = read_curve(tmp_path)
    assert cols["step"].tolist() == [5, 10, 15, 20]
    assert cols["wall_s"].tolist() == [1.0, 2.0, 3.0, 5.5]


def test_one_checkpoint_cannot_resume_several_segments(data_dir: Path, tmp_path: Path):
    cfg = tiny_config(data_dir, "trainer.max_steps=2", "+scene.segments=[[0,510],[490,1000]]",
                      f"ckpt_path={tmp_path / 'x.ckpt'}")
    with pytest.raises(InputError, match=r"ckpt_path: expected 'last', or one checkpoint "
                                         r"with data\.segment=K"):
        runner.run(cfg, tmp_path / "run")


def test_a_longer_trained_segment_is_not_silently_reused(data_dir: Path, tmp_path: Path):
    runner.run(tiny_config(data_dir, "trainer.max_steps=6", "evaluate=false"), tmp_path)
    shorter = tiny_config(data_dir, "trainer.max_steps=4", "evaluate=false")
    with pytest.raises(InputError, match=r"last\.ckpt: global_step: expected at most this "
                                         r"run's 4 steps per segment.*got 6"):
        runner.run(shorter, tmp_path)
    longer = runner.run(tiny_config(data_dir, "trainer.max_steps=8", "evaluate=false"), tmp_path)
    assert longer["steps"] == 8  # resumed from step 6 and trained on


def _lr_per_step(cfg) -> list[float]:
    """The lr of the first parameter group after each step of a ``cfg.trainer.max_steps``
    fit of a fresh module of ``cfg``."""
    ds = build.load_dataset(cfg)
    module = build.build_module(cfg, build.scene_properties(cfg, ds), ds.splits["train"],
                                Segment(0, 1000))
    seen: list[float] = []

    class Probe(L.Callback):
        def on_train_batch_end(self, trainer, *_):
            seen.append(trainer.optimizers[0].param_groups[0]["lr"])

    L.Trainer(max_steps=int(cfg.trainer.max_steps), logger=False, enable_checkpointing=False,
              callbacks=[Probe()], enable_progress_bar=False, enable_model_summary=False,
              accelerator="cpu").fit(module)
    return seen


def test_lr_decays_exponentially_to_the_end_factor(data_dir: Path):
    cfg = tiny_config(data_dir, "trainer.max_steps=8", "trainer.lr_end_factor=0.1",
                      "trainer.lr_decay_start=0")
    lr0 = float(cfg.model.optim.lr)
    # lr_s = lr0 · 0.1^(s / 8): 1× at the first step, 0.1^(7/8)× at the last of 8
    assert _lr_per_step(cfg) == pytest.approx([lr0 * 0.1 ** (s / 8) for s in range(8)],
                                              rel=1e-9)
    with pytest.raises(InputError, match="trainer.lr_end_factor"):
        build.build_module(tiny_config(data_dir, "trainer.lr_end_factor=1.5"),
                           build.scene_properties(cfg, build.load_dataset(cfg)), None,
                           Segment(0, 1000))


def test_lr_warms_up_linearly_then_decays(data_dir: Path):
    cfg = tiny_config(data_dir, "trainer.max_steps=8", "trainer.lr_warmup=4",
                      "trainer.lr_end_factor=0.5", "trainer.lr_decay_start=0")
    lr0 = float(cfg.model.optim.lr)
    # lr_s = lr0 · min(1, s/4) · 0.5^(s/8): 0 at the first step (the authors' it/4000)
    assert _lr_per_step(cfg) == pytest.approx(
        [lr0 * min(1.0, s / 4) * 0.5 ** (s / 8) for s in range(8)], rel=1e-9)
    with pytest.raises(InputError, match="trainer.lr_warmup"):
        build.build_module(tiny_config(data_dir, "trainer.lr_warmup=2.5"),
                           build.scene_properties(cfg, build.load_dataset(cfg)), None,
                           Segment(0, 1000))


def test_a_late_decay_holds_the_lr_then_decays_and_the_record_and_tables_say_so(
        data_dir: Path, tmp_path: Path):
    cfg = tiny_config(data_dir, "trainer.max_steps=8", "trainer.lr_end_factor=0.1",
                      "trainer.lr_decay_start=0.5")
    lr0 = float(cfg.model.optim.lr)
    # constant up to step 4 = 0.5 · 8 (steps 0-4), then lr0 · 0.1^((s − 4) / 4)
    assert _lr_per_step(cfg) == pytest.approx(
        [lr0] * 5 + [lr0 * 0.1 ** ((s - 4) / 4) for s in (5, 6, 7)], rel=1e-9)
    assert records.run_info(cfg, {})["lr_decay_start"] == 0.5
    # without a decay its start changes nothing, and the record says 0 (the tables' jobs)
    assert records.run_info(tiny_config(data_dir, "trainer.lr_end_factor=1.0",
                                        "trainer.lr_decay_start=0.5"), {})["lr_decay_start"] == 0
    from eventrecon.evaluation.summary import format_summary
    from eventrecon.report.cells import method_notes
    from eventrecon.report.runs import _job, collect_runs
    info = {**records.run_info(cfg, {}), "status": "ok", "psnr": 25.0}
    records.write_metrics(tmp_path / "r" / "0", info)
    notes = " ".join(method_notes(collect_runs([tmp_path / "r"])))
    assert "decayed exponentially to 0.1× of its start by the last step" in notes
    assert "after a constant lr for the first 50% of the steps (trainer.lr_decay_start)" in notes
    assert "lr held for the first 50% of the steps, then decayed to 0.1× by the last step" in \
        format_summary(info, tmp_path)
    # a record from before the key existed stands for a decay from the first step
    old = {k: v for k, v in info.items() if k != "lr_decay_start"}
    records.write_metrics(tmp_path / "o" / "0", {**old, "lr_decay_start": 0.0})
    records.write_metrics(tmp_path / "o" / "1", old)
    a, b = collect_runs([tmp_path / "o"])
    assert _job(a) == _job(b)
    props = build.scene_properties(cfg, build.load_dataset(cfg))
    for bad in ("1.0", "-0.1", "true"):
        with pytest.raises(InputError, match=r"trainer\.lr_decay_start"):
            build.build_module(tiny_config(data_dir, f"trainer.lr_decay_start={bad}"), props,
                               None, Segment(0, 1000))


def test_renderers_take_the_runs_mixed_precision_for_images_and_the_record_says_so(
        data_dir: Path, monkeypatch) -> None:
    from eventrecon.config import precision

    monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: True)
    cfg = tiny_config(data_dir, "trainer.lightning.precision=bf16-mixed")
    ds = build.load_dataset(cfg)
    props = build.scene_properties(cfg, ds)
    assert build.build_renderer(cfg.render, props, "bf16-mixed").image_dtype == torch.bfloat16
    assert build.build_renderer(cfg.render, props, "32-true").image_dtype is None
    assert records.run_info(cfg, {})["image_autocast"] is True
    off = tiny_config(data_dir, "trainer.lightning.precision=bf16-mixed",
                      "render.image_autocast=false")
    assert build.build_renderer(off.render, props, "bf16-mixed").image_dtype is None
    assert records.run_info(off, {})["image_autocast"] is False
    fp32 = tiny_config(data_dir, "trainer.lightning.precision=32-true")
    assert records.run_info(fp32, {})["image_autocast"] is False
    # fp16 (a GPU's precision) on a CPU, and bf16 on a CPU without it: images in fp32
    fp16 = tiny_config(data_dir, "trainer.lightning.precision=16-mixed")
    assert records.run_info(fp16, {})["image_autocast"] is False
    monkeypatch.setattr(precision, "cpu_has_native_bf16", lambda: False)
    assert records.run_info(cfg, {})["image_autocast"] is False


def test_adamw_runs_fused_with_the_unfused_update_up_to_rounding(data_dir: Path):
    """The module's AdamW is the fused kernel on CPU parameters; over 30 steps of random
    gradients its parameters stay within rounding of the loop implementation's."""
    cfg = tiny_config(data_dir)
    props = build.scene_properties(cfg, build.load_dataset(cfg))
    m = build.build_module(cfg, props, None, Segment(0, 1000))
    reference = copy.deepcopy(m.field)
    fused = m.configure_optimizers()
    assert fused.defaults["fused"] is True
    loop = torch.optim.AdamW(reference.parameters(), lr=fused.defaults["lr"],
                             betas=fused.defaults["betas"], eps=fused.defaults["eps"],
                             weight_decay=fused.defaults["weight_decay"], foreach=False)
    start = [p.detach().clone() for p in reference.parameters()]
    g = torch.Generator().manual_seed(3)
    for _ in range(30):
        for a, b in zip(m.field.parameters(), reference.parameters()):
            a.grad = torch.randn(a.shape, generator=g)
            b.grad = a.grad.clone()
        fused.step()
        loop.step()
    moved = min(float((b - b0).abs().max()) for b, b0 in zip(reference.parameters(), start))
    diff = max(float((a - b).abs().max())
               for a, b in zip(m.field.parameters(), reference.parameters()))
    assert moved > fused.defaults["lr"]                # every tensor took real steps ...
    assert diff <= 1e-3 * moved                        # ... the same ones, up to rounding


def test_betas_power_raises_adams_betas_and_the_record_and_tables_say_so(data_dir: Path,
                                                                        tmp_path: Path):
    cfg = tiny_config(data_dir, "model.optim.betas_power=10")
    props = build.scene_properties(cfg, build.load_dataset(cfg))
    opt = build.build_module(cfg, props, None, Segment(0, 1000)).configure_optimizers()
    # (0.9, 0.999)^10: the moments forget over the same path length at 10x the lr
    assert opt.param_groups[0]["betas"] == pytest.approx((0.3486784401, 0.9900448802),
                                                         rel=1e-9)
    assert records.run_info(cfg, {})["betas_power"] == 10.0
    authors = tiny_config(data_dir, "model.optim.betas_power=1")
    assert records.run_info(authors, {})["betas_power"] == 1.0
    assert build.adam_betas(authors) == (0.9, 0.999)
    from eventrecon.report.cells import method_notes
    from eventrecon.report.runs import collect_runs
    records.write_metrics(tmp_path / "r" / "0", {**records.run_info(cfg, {}),
                                                 "status": "ok", "psnr": 25.0})
    notes = " ".join(method_notes(collect_runs([tmp_path / "r"])))
    assert "Adam's betas raised to the power 10 (model.optim.betas_power" in notes
    for bad, field in (("model.optim.betas_power=0", "model.optim.betas_power"),
                       ("model.optim.betas=[0.9,1.0]", "model.optim.betas")):
        with pytest.raises(InputError, match=field.replace(".", r"\.")):
            build.build_module(tiny_config(data_dir, bad), props, None, Segment(0, 1000))


def test_a_segment_trained_by_an_older_method_version_trains_again(
        data_dir: Path, tmp_path: Path, monkeypatch, caplog):
    old = records.METHOD_VERSION
    runner.run(tiny_config(data_dir, "trainer.max_steps=4", "evaluate=false"), tmp_path)
    seg = tmp_path / "seg0"
    assert json.loads((seg / "done.json").read_text())["method_version"] == old
    monkeypatch.setattr(records, "METHOD_VERSION", old + 1)   # the method changed since
    with caplog.at_level("WARNING", logger="eventrecon.engine.runner"):
        again = runner.run(tiny_config(data_dir, "trainer.max_steps=4", "evaluate=false"),
                           tmp_path)
    assert f"trained by method version {old} (now {old + 1})" in caplog.text
    assert (seg / "checkpoints" / f"last.method_v{old}.ckpt").is_file()   # kept, not resumed
    state = torch.load(seg / "checkpoints" / "last.ckpt", weights_only=False)
    assert state["eventrecon"]["method_version"] == old + 1 and state["global_step"] == 4
    assert json.loads((seg / "done.json").read_text())["method_version"] == old + 1
    assert again["method_version"] == old + 1


def test_a_segment_trained_on_other_data_trains_again(data_dir: Path, tmp_path: Path, caplog):
    # the same job on a changed dataset (a simulated scene's folder name carries its spec's
    # hash): its records and checkpoint are stale; on the same data the segment is kept
    root = dataset_path(tiny_config(data_dir).scene, data_dir)
    changed = tmp_path / "changed-scene"
    shutil.copytree(root, changed)
    out, seg = tmp_path / "run", tmp_path / "run" / "seg0"
    for data in (root, root):
        with caplog.at_level("INFO", logger="eventrecon.engine.runner"):
            runner.run(tiny_config(data_dir, f"data.root={data}", "trainer.max_steps=4",
                                   "evaluate=false"), out)
    assert "trained before" in caplog.text and "kept as" not in caplog.text
    assert json.loads((seg / "done.json").read_text())["data_id"] == root.name
    with caplog.at_level("WARNING", logger="eventrecon.engine.runner"):
        again = runner.run(tiny_config(data_dir, f"data.root={changed}", "trainer.max_steps=4",
                                       "evaluate=false"), out)
    assert f"trained on {root.name} (now changed-scene)" in caplog.text
    assert (seg / "checkpoints" / f"last.data_{root.name}.ckpt").is_file()   # kept, not resumed
    state = torch.load(seg / "checkpoints" / "last.ckpt", weights_only=False)
    assert state["eventrecon"]["data_id"] == "changed-scene" and state["global_step"] == 4
    assert json.loads((seg / "done.json").read_text())["data_id"] == "changed-scene"
    assert again["data_id"] == "changed-scene"
    assert records.finished_metrics(out / "metrics.json", 4, False, 4, root.name) is None


def test_the_module_lays_loaded_adamw_moments_out_as_their_parameters(data_dir: Path):
    """``configure_optimizers`` registers ``state_like_params``: moments saved in another
    layout (here column-major copies of the weights' moments, the same values) come back
    with their parameters' strides, which the fused kernel's flat walk needs."""
    cfg = tiny_config(data_dir)
    props = build.scene_properties(cfg, build.load_dataset(cfg))
    m = build.build_module(cfg, props, None, Segment(0, 1000))
    opt = m.configure_optimizers()
    for p in m.field.parameters():
        p.grad = torch.randn_like(p)
    opt.step()
    saved = copy.deepcopy(opt.state_dict())
    moved = 0
    for state in saved["state"].values():
        for key, value in state.items():
            if value.dim() == 2:
                state[key] = value.t().contiguous().t()
                moved += 1
    assert moved > 0
    fresh = m.configure_optimizers()
    fresh.load_state_dict(saved)
    for p in m.field.parameters():
        for key, value in fresh.state[p].items():
            if value.dim():
                assert value.stride() == p.stride(), key
            assert torch.equal(value, opt.state[p][key])
