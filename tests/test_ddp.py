"""``trainer=ddp``'s code path on CPU: two processes (gloo), rank-specific rays, rank 0
alone writes the curve, the segment record and the metrics."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import torch
from integration import TINY, TINY_NERF

from eventrecon.engine.module import step_generator

ROOT = Path(__file__).resolve().parents[1]


def test_ranks_draw_different_batches_from_one_step():
    a = torch.rand(8, generator=step_generator(0, 5, stream=0))
    b = torch.rand(8, generator=step_generator(0, 5, stream=1))
    again = torch.rand(8, generator=step_generator(0, 5, stream=1))
    assert not torch.equal(a, b) and torch.equal(b, again)


def test_two_process_ddp_run_on_cpu(tmp_path: Path):
    run = tmp_path / "run"
    cmd = [sys.executable, str(ROOT / "train.py"), *TINY, *TINY_NERF,
           f"data_dir={tmp_path / 'data'}", "trainer.max_steps=6", "trainer.curve_every=2",
           "+trainer.lightning.strategy=ddp", "trainer.lightning.devices=2",
           f"hydra.run.dir={run}"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "EVENTRECON_OFFLINE": "1"}
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Starting with 2 processes" in proc.stdout + proc.stderr
    metrics = json.loads((run / "metrics.json").read_text())
    # 6 steps: "collapsed" (at the empty field) is a possible verdict, "failed" is not
    assert metrics["status"] in ("ok", "collapsed")
    assert metrics["steps"] == 6 and metrics["psnr"] > 10
    with (run / "seg0" / "curve.csv").open() as f:
        steps = [int(r["step"]) for r in csv.DictReader(f)]
    assert steps == [2, 4, 6, 6]  # one row per evaluation (rank 0 only): cheap x3, full
    assert json.loads((run / "seg0" / "done.json").read_text())["steps"] == 6
