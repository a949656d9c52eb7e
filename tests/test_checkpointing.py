"""Atomic writes: a failed write keeps the old file; a killed one leaves only a temporary
that the next run removes."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from eventrecon.common.files import atomic_write_json, atomic_write_with, remove_stale_temporaries


def test_failed_write_keeps_the_old_file_and_no_temporary(tmp_path: Path):
    target = tmp_path / "metrics.json"
    atomic_write_json(target, {"psnr": 21.5})

    def explode(f) -> None:
        f.write(b"{\"psnr\": ")  # half a file, then a crash
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        atomic_write_with(target, explode)
    assert json.loads(target.read_text()) == {"psnr": 21.5}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json"]


def test_sigkill_during_a_write_leaves_the_target_intact_and_a_removable_temporary(
        tmp_path: Path):
    target = tmp_path / "last.ckpt"
    target.write_bytes(b"old checkpoint")
    started = tmp_path / "started"
    # a writer that blocks half-way through its write until it is killed
    code = (
        "import sys, time, pathlib\n"
        "from eventrecon.engine.checkpointing import atomic_write_with\n"
        "def w(f):\n"
        "    f.write(b'new, half written'); f.flush()\n"
        f"    pathlib.Path({str(started)!r}).touch()\n"
        "    time.sleep(60)\n"
        f"atomic_write_with({str(target)!r}, w)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code])
    deadline = time.time() + 60
    while not started.exists() and time.time() < deadline:
        time.sleep(0.02)
    assert started.exists()
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert target.read_bytes() == b"old checkpoint"
    stale = list(tmp_path.glob(".last.ckpt.*.tmp"))
    assert len(stale) == 1 and stale[0].read_bytes() == b"new, half written"
    assert remove_stale_temporaries(tmp_path) == stale
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.ckpt", "started"]
    assert remove_stale_temporaries(tmp_path / "missing") == []
