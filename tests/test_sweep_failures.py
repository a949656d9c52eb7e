"""A sweep with one failing job completes the others, records and reports the failure.

``python train.py -m scale=smoke data.views=2,99,3``: the job with 99 views (the dataset
has 6) fails with a one-line InputError; the other two train and evaluate. Every job
folder then holds ``metrics.json`` (``status`` ok / failed with the error text). Running
the same sweep again skips the finished jobs (their ``metrics.json`` untouched) and
retries the failed one. ``python -m eventrecon.report`` counts the failure and shows
"failed" in Tab. 7's 99-views row, next to the two finished rows.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
from integration import tiny_config

from eventrecon.engine import build, runner
from eventrecon.sim.pipeline import ensure_dataset

ROOT = Path(__file__).resolve().parents[1]
VIEWS = (2, 99, 3)
IDENTITY = ("scene", "model", "loss", "views", "fps")


def _env(data_dir: Path) -> dict[str, str]:
    return {**os.environ, "OMP_NUM_THREADS": "1", "EVENTRECON_OFFLINE": "1",
            "EVENTRECON_DATA": str(data_dir)}


def _sweep(data_dir: Path, sweep_dir: Path) -> str:
    cmd = [sys.executable, str(ROOT / "train.py"), "-m", "scale=smoke",
           f"data.views={','.join(map(str, VIEWS))}", f"hydra.sweep.dir={sweep_dir}"]
    proc = subprocess.run(cmd, env=_env(data_dir), capture_output=True, text=True, timeout=300)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]  # the failing job does not stop the sweep
    return out


def _job(sweep_dir: Path, views: int) -> Path:
    """A job's folder: its overrides, ``scale`` included (smoke and cpu runs stay apart)."""
    return sweep_dir / f"data.views={views},scale=smoke"


def _metrics(sweep_dir: Path) -> dict[int, dict]:
    return {v: json.loads((_job(sweep_dir, v) / "metrics.json").read_text()) for v in VIEWS}


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("data")
    # scale=smoke's scene is 32x24, the same scene (and cache entry) as tiny_config's
    ensure_dataset(tiny_config(path).scene, path)
    return path


def test_failing_job_is_recorded_skipped_on_rerun_and_reported(data_dir: Path, tmp_path: Path):
    sweep = tmp_path / "sweep"
    out = _sweep(data_dir, sweep)
    jobs = sorted(p.name for p in sweep.iterdir() if (p / ".hydra").is_dir())
    assert jobs == sorted(_job(sweep, v).name for v in VIEWS)
    m = _metrics(sweep)
    error = ("InputError: config: data.views: expected an integer in [1, 6] "
             "(views in the dataset), got 99")
    assert m[99]["status"] == "failed" and m[99]["error"] == error
    assert out.count("job failed: config: data.views") == 1
    for v in (2, 3):
        assert m[v]["status"] == "ok" and m[v]["error"] is None
        assert m[v]["views"] == v and m[v]["steps"] == 6
        assert math.isfinite(m[v]["psnr"]) and m[v]["psnr"] > 10.0
    # the failure carries the identity a finished run would have: same cell in the report
    assert {k: m[99][k] for k in IDENTITY} == {**{k: m[2][k] for k in IDENTITY}, "views": 99}

    stamps = {v: (_job(sweep, v) / "metrics.json").stat().st_mtime_ns for v in VIEWS}
    out = _sweep(data_dir, sweep)
    assert out.count("finished before, skipped") == 2
    assert f"{_job(sweep, 2)}: finished before, skipped" in out
    assert out.count("job failed: config: data.views") == 1  # the failed job was retried
    again = {v: (_job(sweep, v) / "metrics.json").stat().st_mtime_ns for v in VIEWS}
    assert again[2] == stamps[2] and again[3] == stamps[3]
    assert again[99] > stamps[99]
    assert _metrics(sweep)[2] == m[2]

    report = tmp_path / "report"
    proc = subprocess.run([sys.executable, "-m", "eventrecon.report", str(sweep),
                           "--out", str(report), "--tables", "table7"],
                          env=_env(data_dir), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "found 3 runs (2 ok)" in proc.stdout + proc.stderr
    paper_part = (report / "table7.md").read_text().split("### Subject region")[0]
    rows = {ln.split("|")[1].strip(): [c.strip() for c in ln.split("|")[2:-1]]
            for ln in paper_part.splitlines()
            if ln.startswith("| ") and ln.split("|")[1].strip().isdigit()}
    assert rows["99"] == ["—", "failed", "—", "0/1 (1 failed)"]
    assert rows["2"][1] == f"{m[2]['psnr']:.2f}" and rows["3"][1] == f"{m[3]['psnr']:.2f}"
    assert rows["4"][1] == "—"  # not run: a dash, never a made-up number


def test_planned_identity_matches_the_finished_run(data_dir: Path, tmp_path: Path):
    """What a failure record says (``planned_run_info``) = what ``run`` would have written."""
    cfg = tiny_config(data_dir, "trainer.max_steps=2", "evaluate=false")
    metrics = runner.run(cfg, tmp_path / "run")
    planned = build.planned_run_info(cfg)
    assert {k: planned[k] for k in IDENTITY} == {k: metrics[k] for k in IDENTITY}
    assert planned["views"] == 6 and planned["fps"] == 5.0
    # no dataset on disk yet (the job failed before simulating): the scene config's values
    fresh = build.planned_run_info(tiny_config(tmp_path / "empty"))
    assert {k: fresh[k] for k in IDENTITY} == {k: metrics[k] for k in IDENTITY}
    assert not (tmp_path / "empty").exists()
