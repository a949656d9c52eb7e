"""A run killed with SIGKILL at random steps resumes from its last checkpoint and ends
with exactly the metrics of an uninterrupted run (same seed, CPU)."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

from integration import TINY, TINY_NERF, tiny_config

from eventrecon.sim.pipeline import ensure_dataset

ROOT = Path(__file__).resolve().parents[1]
STEPS = 120


def _cmd(data_dir: Path, run_dir: Path) -> list[str]:
    return [sys.executable, str(ROOT / "train.py"), *TINY, *TINY_NERF, f"data_dir={data_dir}",
            f"trainer.max_steps={STEPS}", "trainer.checkpoint_every=4",
            f"hydra.run.dir={run_dir}"]


def _env() -> dict[str, str]:
    return {**os.environ, "OMP_NUM_THREADS": "1", "EVENTRECON_OFFLINE": "1"}


def test_sigkill_then_resume_gives_identical_metrics(tmp_path: Path):
    data_dir = tmp_path / "data"
    ensure_dataset(tiny_config(data_dir).scene, data_dir)
    ref_dir, run_dir = tmp_path / "ref", tmp_path / "killed"
    subprocess.run(_cmd(data_dir, ref_dir), check=True, env=_env(), capture_output=True)
    reference = json.loads((ref_dir / "metrics.json").read_text())

    rng = random.Random(0)
    last = run_dir / "seg0" / "checkpoints" / "last.ckpt"
    kills = 0
    for _ in range(3):
        if (run_dir / "metrics.json").exists():
            break  # the previous attempt finished before the kill landed
        proc = subprocess.Popen(_cmd(data_dir, run_dir), env=_env(),
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        seen = last.stat().st_mtime_ns if last.exists() else None
        deadline = time.time() + 120
        while time.time() < deadline and proc.poll() is None:
            if last.exists() and last.stat().st_mtime_ns != seen:
                break  # a (new) checkpoint exists: now kill at a random moment
            time.sleep(0.02)
        time.sleep(rng.uniform(0.0, 1.0))
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            kills += 1
    assert kills >= 1, "the run finished before it could be killed; lengthen it"
    subprocess.run(_cmd(data_dir, run_dir), check=True, env=_env(), capture_output=True)
    resumed = json.loads((run_dir / "metrics.json").read_text())
    assert resumed["steps"] == reference["steps"] == STEPS
    for key in ("psnr", "ssim"):
        assert resumed[key] == reference[key], key  # exactly, not approximately
    # no stray temporary files from the killed writes are left next to the checkpoints
    assert not list((run_dir / "seg0" / "checkpoints").glob("*.tmp"))
