"""Runs people can watch: progress lines without a terminal, the end-of-run summary, and
runs on a dataset folder named after the dataset everywhere."""

from __future__ import annotations

import json
import logging
import re
import shutil
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from integration import tiny_config
from omegaconf import OmegaConf

from eventrecon.common.progress import TaskProgress
from eventrecon.engine import progress as progress_mod
from eventrecon.engine import runner
from eventrecon.engine.progress import Progress
from eventrecon.evaluation.summary import format_summary
from eventrecon.results.records import run_info

LINE = re.compile(r"^segment 2/5  step (\d+)/(\d+) \((\d+)%\)  loss (\S+)  (\S+) s/it  "
                  r"eta (\S+)  psnr (.+)$")


class _Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_log_lines_carry_every_field_and_come_every_30_s(monkeypatch, caplog):
    clock = _Clock()
    monkeypatch.setattr(progress_mod.time, "perf_counter", clock)
    monitor = SimpleNamespace(last_psnr=None)
    cb = Progress(1, 5, mode="log", every_s=30.0, monitor=monitor)
    trainer = SimpleNamespace(is_global_zero=True, global_step=0, max_steps=1000)
    caplog.set_level(logging.INFO, logger="eventrecon.engine.progress")
    cb.on_train_start(trainer, None)
    times = []
    for step in range(1, 1001):
        clock.now += 0.25  # 0.25 s a step: a line every 120 steps
        trainer.global_step = step
        if step == 500:
            monitor.last_psnr = 24.316
        n = len(caplog.records)
        cb.on_train_batch_end(trainer, None, {"loss": torch.tensor(0.2081)}, None, step)
        if len(caplog.records) > n:
            times.append(clock.now)
    lines = [r.getMessage() for r in caplog.records]
    assert all("\r" not in ln and "\n" not in ln for ln in lines)
    parsed = [LINE.match(ln) for ln in lines]
    assert all(parsed), lines
    gaps = [b - a for a, b in zip(times, times[1:])]
    assert all(30.0 <= g < 30.5 for g in gaps[:-1]) and len(lines) == 9  # 8 due + the last
    first, last = parsed[0].groups(), parsed[-1].groups()
    assert first[:3] == ("120", "1000", "12") and first[3] == "0.2081"
    assert float(first[4]) == pytest.approx(0.25) and first[5] == "3m40s"  # 880 steps left
    assert first[6] == "—" and last[:3] == ("1000", "1000", "100") and last[6] == "24.32 dB"


def test_a_resumed_segment_counts_its_rate_from_the_resumed_step(monkeypatch, caplog):
    clock = _Clock()
    monkeypatch.setattr(progress_mod.time, "perf_counter", clock)
    cb = Progress(1, 5, mode="log", every_s=1.0)
    trainer = SimpleNamespace(is_global_zero=True, global_step=600, max_steps=1000)
    caplog.set_level(logging.INFO, logger="eventrecon.engine.progress")
    cb.on_train_start(trainer, None)
    clock.now += 2.0
    trainer.global_step = 610
    cb.on_train_batch_end(trainer, None, {"loss": torch.tensor(0.5)}, None, 0)
    assert "step 610/1000 (61%)" in caplog.records[-1].getMessage()
    assert "0.200 s/it  eta 1m18s" in caplog.records[-1].getMessage()


def test_task_progress_lines_for_long_work(monkeypatch, caplog):
    clock = _Clock()
    monkeypatch.setattr(progress_mod.time, "perf_counter", clock)
    caplog.set_level(logging.INFO, logger="eventrecon.engine.progress")
    p = TaskProgress("held-out renders", 11, every_s=30.0)
    for _ in range(11):
        clock.now += 20.0  # 20 s an image: a line every second image, and the last
        p.step()
    msgs = [r.getMessage() for r in caplog.records]
    assert msgs[0] == "held-out renders: 2/11 (18%)  20.00 s each  eta 3m00s"
    assert msgs[-1].startswith("held-out renders: 11/11 (100%)") and len(msgs) == 6


def test_summary_names_the_result_its_cost_and_where_to_look():
    m = {"scene": "sword", "model": "nerf", "loss": "full", "seed": 1, "status": "collapsed",
         "collapse_reason": "segment 0: mean opacity below 0.001", "psnr": 26.2,
         "psnr_background": 26.2, "steps": 1000, "wall_s": 61.0, "sec_per_it": 0.061,
         "total_s": 90.0, "peak_mem_mb": 800.0, "lpips": None, "lpips_note": "no weights",
         "schedule": "compressed", "sizing": "cpu_nerf", "skip": "grid"}
    text = format_summary(m, "outputs/sword/run")
    assert text.splitlines()[0] == "run summary — sword · nerf · full · seed 1"
    assert "COLLAPSED — renders the empty field (segment 0" in text
    assert "(empty field 26.20 dB: +0.00 dB)" in text and "LPIPS-Alex      n/a (no weights)" in text
    assert "1000 steps in 1m01s (0.061 s/it); 1m30s in all" in text and "0.8 GB" in text
    assert "schedules compressed; size conf/sizing/cpu_nerf.yaml; empty-space skipping" in text
    assert "outputs/sword/run/renders/" in text and "make tensorboard" in text


def test_runs_on_a_dataset_folder_are_named_after_the_dataset(tmp_path: Path):
    """The output folder, metrics.json and the log use the dataset's name: its meta.json
    ``scene_name``, else the folder's name; never the default scene's."""
    data = tmp_path / "data"
    cfg = tiny_config(data, "trainer.max_steps=2", "evaluate=false")
    from eventrecon.engine.build import load_dataset

    src = load_dataset(cfg).root
    sword = tmp_path / "sword"
    shutil.copytree(src, sword)
    meta = json.loads((sword / "meta.json").read_text())
    meta.pop("scene", None)
    (sword / "meta.json").write_text(json.dumps(meta))
    run_cfg = tiny_config(data, "trainer.max_steps=2", "evaluate=false", f"data.root={sword}")
    from eventrecon.config.resolvers import run_data_name

    assert run_data_name(_root_=run_cfg) == "sword"
    assert run_info(run_cfg, meta)["scene"] == "sword"
    metrics = runner.run(run_cfg, tmp_path / "out")
    assert metrics["scene"] == "sword"
    meta["scene_name"] = "sword_take2"
    (sword / "meta.json").write_text(json.dumps(meta))
    assert run_data_name(_root_=run_cfg) == "sword_take2"
    # the Hydra output folder follows
    conf = OmegaConf.load(Path(__file__).resolve().parents[1] / "conf" / "config.yaml")
    assert OmegaConf.to_container(conf)["hydra"]["run"]["dir"].startswith("outputs/${data_name:}/")
