"""``python train.py -m experiment=table3 scale=smoke`` end to end, then the report.

The sweep trains every row of the supplementary's Tab. 3 on two of its five scenes
(``spheres`` and ``static_lego``: the sweep's scene list is narrowed to keep the test
short) for a few steps; the report must show every row and column of Tab. 3 in the
paper's order, the paper's numbers in place, and a number of ours (not "—") in every row
of the columns that were run.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from test_report import _parse_md

from eventrecon.report import collect_runs
from eventrecon.report.paper import PAPER_TABLES
from eventrecon.report.tables import build_table, to_markdown

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def table3_sweep(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("table3")
    env = {**os.environ, "OMP_NUM_THREADS": "1", "EVENTRECON_OFFLINE": "1",
           "EVENTRECON_DATA": str(tmp / "data")}
    cmd = [sys.executable, str(ROOT / "train.py"), "-m", "experiment=table3", "scale=smoke",
           "scene=spheres,static_lego", f"hydra.sweep.dir={tmp / 'sweep'}"]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    return tmp / "sweep"


def test_table3_smoke_sweep_fills_every_row_and_column(table3_sweep: Path):
    runs = collect_runs([table3_sweep])
    paper = PAPER_TABLES["table3"]
    assert len(runs) == 2 * len(paper.rows)  # every row on spheres and static_lego
    assert all(r.status == "ok" and r.experiment == "table3" for r in runs)
    md = to_markdown(build_table("table3", runs)).split("### Subject region")[0]
    groups = _parse_md(md)
    titles = list(groups)
    assert [t.split(" — ")[0] for t in titles] == [*paper.columns]
    for title, col in zip(titles, paper.columns):
        assert list(groups[title]) == list(paper.rows), title
        for row in paper.rows:
            cells = groups[title][row]
            for m, metric in enumerate(("PSNR↑", "SSIM↑", "LPIPS-Alex↓")):
                want = f"{paper.value(row, col)[m]:.3f}" if col else "—"
                assert cells[f"{metric} paper"] == want, (title, row, metric)
    # Spheres <- spheres, Static Lego <- static_lego, then Average
    ours = {"spheres": titles[2], "static_lego": titles[4], "avg": titles[5]}
    assert "`spheres`" in titles[2] and "`static_lego`" in titles[4]
    for title in ours.values():
        for row in paper.rows:
            psnr = groups[title][row]["PSNR↑ ours"]
            assert float(psnr) > 0, (title, row, psnr)  # a measured number, not "—"
            assert float(groups[title][row]["SSIM↑ ours"]) <= 1.0
