"""Reports: Tab. 3–7 in the paper's layout beside fake runs; accuracy vs time."""

from __future__ import annotations

import json
import math
import os
import re
import struct
from pathlib import Path

import numpy as np
import pytest

from eventrecon.report import build_report, collect_runs
from eventrecon.report.__main__ import main
from eventrecon.report.budgets import budget_markdown, psnr_within
from eventrecon.report.curves import summarize, time_to_level, trailing_median
from eventrecon.report.paper import PAPER_TABLES
from eventrecon.report.runs import write_curve, write_run
from eventrecon.report.tables import build_table, to_latex, to_markdown

SEED_TEXT = Path("/work/shared/seed/dynamic-eventnerf-supplementary.txt")


def _metrics(scene, model="nerf", loss="full", views=5, fps=5.0, psnr=25.0, ssim=0.9,
             lpips=0.1, status="ok", **kw):
    return dict(scene=scene, model=model, loss=loss, views=views, fps=fps, psnr=psnr,
                ssim=ssim, lpips=lpips, lpips_note=None if lpips is not None else "no weights",
                wall_s=100.0, steps=1000, sec_per_it=0.1, peak_mem_mb=512.0, status=status,
                error=None if status == "ok" else "boom", **kw)


def _sweep(root: Path, jobs: list[dict], experiment: str | None = None) -> Path:
    sweep = root / "multirun" / "2025-01-01" / "12-00-00"
    for i, m in enumerate(jobs):
        job = write_run(sweep / str(i), m)
        if experiment:
            (job / ".hydra").mkdir()
            (job / ".hydra" / "overrides.yaml").write_text(
                f"- experiment={experiment}\n- model={m['model']}\n- loss={m['loss']}\n"
            )
    return sweep


def _parse_md(text: str) -> dict[str, dict[str, dict[str, str]]]:
    """``{group title: {row label: {column header: cell}}}`` from our Markdown."""
    groups: dict[str, dict[str, dict[str, str]]] = {}
    title = None
    header: list[str] = []
    for line in text.splitlines():
        if line.startswith("### "):
            title, header = line[4:], []
            groups[title] = {}
        elif line.startswith("|") and title:
            cells = [c.strip() for c in line.strip("|").split("|")]
            if not header:
                header = cells
            elif not set(cells[0]) <= set(":-"):
                groups[title][cells[0]] = dict(zip(header, cells))
    return groups


@pytest.fixture
def table3_sweep(tmp_path):
    jobs = [
        _metrics("spheres", psnr=30.0, ssim=0.93, lpips=0.08),
        _metrics("blocks", psnr=26.0, ssim=0.89, lpips=0.12),
        _metrics("spheres", loss="no_event", psnr=28.0, ssim=0.91, lpips=None),
        _metrics("spheres", model="ngp", psnr=20.0, ssim=0.80, lpips=0.3, status="failed"),
        _metrics("blocks", model="hexplane", psnr=22.5, ssim=0.85, lpips=0.25),
        # not a Tab. 3 row (no_decay is Tab. 4 only): must be ignored
        _metrics("spheres", loss="no_decay", psnr=99.0),
    ]
    return _sweep(tmp_path, jobs, "table3")


def test_table3_layout_paper_numbers_ours_and_deltas(table3_sweep):
    runs = collect_runs([table3_sweep.parent.parent])
    assert len(runs) == 6 and all(r.experiment == "table3" for r in runs)
    md = to_markdown(build_table("table3", runs))
    groups = _parse_md(md)
    paper = PAPER_TABLES["table3"]
    titles = list(groups)
    # every paper column, in order, then our extra scene, then the average
    assert [t.split(" — ")[0] for t in titles] == [
        "Blender", "Dress", "Spheres", "Lego", "Static Lego", "— (no paper counterpart)",
        "Average"]
    assert "`spheres`" in titles[2] and "`blocks`" in titles[5]
    for title, col in zip(titles, list(paper.columns[:5]) + [None, "Average"]):
        rows = groups[title]
        assert list(rows) == list(paper.rows)  # every row, in the paper's order
        for row in paper.rows:
            for m, metric in enumerate(("PSNR↑", "SSIM↑", "LPIPS-Alex↓")):
                want = f"{paper.value(row, col)[m]:.3f}" if col else "—"
                assert rows[row][f"{metric} paper"] == want
    sph, blk, avg = groups[titles[2]], groups[titles[5]], groups[titles[6]]
    # ours and Δ where given
    assert sph["Full Model"]["PSNR↑ ours"] == "30.000"
    assert sph["Full Model"]["PSNR↑ Δ"] == f"{30.0 - 29.765:+.3f}" == "+0.235"
    assert sph["Full Model"]["LPIPS-Alex↓ Δ"] == f"{0.08 - 0.081:+.3f}"
    assert sph["w/o L_event"]["SSIM↑ ours"] == "0.910"
    assert sph["w/o L_event"]["LPIPS-Alex↓ ours"] == "n/a"
    assert sph["w/o L_event"]["LPIPS-Alex↓ Δ"] == "—"
    assert sph["NGP"]["PSNR↑ ours"] == "failed" and sph["NGP"]["PSNR↑ Δ"] == "—"
    assert sph["TensoRF-CP"]["PSNR↑ ours"] == "—"
    assert blk["HexPlane"]["PSNR↑ ours"] == "22.500" and blk["HexPlane"]["PSNR↑ Δ"] == "—"
    assert all(groups[titles[0]][r]["PSNR↑ ours"] == "—" for r in paper.rows)
    assert "99.000" not in md
    # averages over our columns with values, Δ against the paper's average
    assert avg["Full Model"]["PSNR↑ ours"] == "28.000"  # (30 + 26) / 2
    assert avg["Full Model"]["PSNR↑ Δ"] == f"{28.0 - 27.097:+.3f}"
    assert avg["Full Model"]["SSIM↑ ours"] == "0.910"
    assert avg["HexPlane"]["PSNR↑ ours"] == "22.500"  # only `blocks` has a value
    assert avg["w/o L_event"]["LPIPS-Alex↓ ours"] == "n/a"  # no LPIPS anywhere in that row
    assert avg["NGP"]["PSNR↑ ours"] == "—"  # failed runs are not averaged
    assert "mean over the columns with a value" in md
    tex = to_latex(build_table("table3", runs))
    assert tex.count(r"\begin{tabular}") == 7 and "29.765 & 30.000 & +0.235" in tex


def test_paper_average_column_is_mean_of_scenes():
    p = PAPER_TABLES["table3"]
    for row in p.rows:
        mean = np.mean([p.value(row, c) for c in p.columns[:5]], axis=0)
        assert np.abs(mean - np.array(p.value(row, "Average"))).max() <= 1.5e-3, row


@pytest.mark.skipif(not SEED_TEXT.is_file(), reason="supplementary text not available")
def test_paper_numbers_match_the_supplementary_text():
    text = SEED_TEXT.read_text()
    nums = {float(x) for x in re.findall(r"\d+\.\d+", text)}
    for t in PAPER_TABLES.values():
        for v in t.values.values():
            assert set(v) <= nums, (t.key, v)
    assert sum(len(v) for t in PAPER_TABLES.values() for v in t.values.values()) == (
        11 * 18 + 14 * 3 + 9 * 3 + 4 * 3 + 7)


def test_tables_4_to_7_rows_and_missing(tmp_path):
    jobs = [
        _metrics("rig_lowlight", loss="no_decay", psnr=24.0, psnr_background=23.0),
        _metrics("rig_lowlight", psnr=25.0, fps=0.5, psnr_background=99.0),  # not kept
        _metrics("rig_lowlight", psnr=26.0, fps=5.0, psnr_background=23.5),
        _metrics("rig_lowlight", psnr=23.0, views=3),
        _metrics("spheres", psnr=20.0, views=2),
        _metrics("spheres", psnr=29.0, views=6),
        _metrics("spheres", psnr=31.0, views=8),
    ]
    runs = collect_runs([_sweep(tmp_path, jobs)])
    t4 = _parse_md(to_markdown(build_table("table4", runs)))
    (title4, rows4), = t4.items()
    assert title4 == "Sword — ours: `rig_lowlight`"
    assert list(rows4) == list(PAPER_TABLES["table4"].rows)
    assert rows4["w/o decay"]["PSNR↑ ours"] == "24.000"
    assert rows4["w/o decay"]["PSNR↑ Δ"] == f"{24.0 - 27.119:+.3f}"
    assert rows4["Our Full Model (Final)"]["PSNR↑ ours"] == "26.000"  # fps=5 is the mode
    md4 = to_markdown(build_table("table4", runs))  # the empty-field score: median of runs
    assert "`rig_lowlight` rendered empty (background only, zero density) scores 23.250 dB" in md4
    t5 = next(iter(_parse_md(to_markdown(build_table("table5", runs))).values()))
    assert t5["0.5"]["PSNR↑ ours"] == "25.000" and t5["5"]["PSNR↑ ours"] == "26.000"
    assert t5["100"]["PSNR↑ ours"] == "—" and t5["100"]["PSNR↑ paper"] == "27.328"
    # another backbone's Tab. 5 sweep fills the table in its own folder, and is never
    # mixed into the NeRF's: the model is held fixed (the mode) and said in a footnote
    grid = collect_runs([_sweep(tmp_path / "grid", [
        _metrics("rig_lowlight", model="hexplane", psnr=27.0, fps=0.5),
        _metrics("rig_lowlight", model="hexplane", psnr=28.0, fps=5.0),
        _metrics("rig_lowlight", model="hexplane", loss="no_event", psnr=99.0, fps=1.0)])])
    md5 = to_markdown(build_table("table5", grid))
    t5g = next(iter(_parse_md(md5).values()))
    assert t5g["0.5"]["PSNR↑ ours"] == "27.000" and t5g["5"]["PSNR↑ ours"] == "28.000"
    assert t5g["1"]["PSNR↑ ours"] == "—" and "at model=hexplane, views=5" in md5
    mixed = next(iter(_parse_md(to_markdown(build_table("table5", runs + grid))).values()))
    assert mixed["0.5"]["PSNR↑ ours"] == "25.000" and mixed["5"]["PSNR↑ ours"] == "26.000"
    t6 = next(iter(_parse_md(to_markdown(build_table("table6", runs))).values()))
    assert t6["3"]["PSNR↑ ours"] == "23.000" and t6["2"]["PSNR↑ ours"] == "—"
    md7 = to_markdown(build_table("table7", runs))
    (title7, t7), = _parse_md(md7).items()
    assert title7 == "Dress — ours: `spheres`"
    assert list(t7) == ["2", "3", "4", "6", "12", "24", "36", "8"]  # our extra view count last
    assert t7["6"]["PSNR↑ ours"] == "29.00" and t7["6"]["PSNR↑ Δ"] == "-1.88"
    assert t7["8"]["PSNR↑ paper"] == "—" and t7["8"]["PSNR↑ ours"] == "31.00"
    assert "SSIM" not in md7


def _curve(wall, psnr, kind):
    return [dict(wall_s=w, step=10 * i, psnr=p, ssim=None, lpips=None, kind=k)
            for i, (w, p, k) in enumerate(zip(wall, psnr, kind))]


def test_accuracy_vs_time_known_curve_and_png(tmp_path):
    wall = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    psnr = [12.0, 21.0, 18.0, 22.0, 26.0, 25.0]
    kind = ["full", "cheap", "full", "full", "cheap", "full"]
    sweep = tmp_path / "sweep"
    write_run(sweep / "0", _metrics("spheres", psnr=25.5), _curve(wall, psnr, kind))
    write_run(sweep / "1", _metrics("spheres", model="ngp", psnr=16.0),
              _curve([0.5, 1.5], [16.0, 17.0], ["cheap", "cheap"]))
    runs = collect_runs([sweep])
    s = summarize(runs[0])
    # every row: (1,12) (2,21) (3,18) (4,22) (5,26) (6,25) → 15 dB at 2 s, 20 at 2 s,
    # 25 at 5 s, 30 never
    assert s.kind == "cheap+full" and s.times == {15.0: 2.0, 20.0: 2.0, 25.0: 5.0, 30.0: None}
    assert s.best_psnr == 26.0
    s1 = summarize(runs[1])
    assert s1.kind == "cheap" and s1.times[15.0] == 0.5 and s1.times[20.0] is None
    assert time_to_level(np.array([3.0, 1.0]), np.array([30.0, np.nan]), 20.0) == 3.0

    out = tmp_path / "results"
    assert main([str(sweep), "--out", str(out)]) == 0
    png = out / "accuracy_vs_time.png"
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
    w, h = struct.unpack(">II", data[16:24])
    assert w > 300 and h > 200
    md = (out / "accuracy_vs_time.md").read_text()
    per_run = md.split("### Per run")[1]
    row = next(line for line in per_run.splitlines() if line.startswith("| nerf"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[3] == "—"  # seed: the fake record has none
    assert cells[4:9] == ["cheap+full", "2.0", "2.0", "5.0", "—"]
    assert cells[9:11] == ["26.00", "25.50"]
    for key in PAPER_TABLES:
        assert (out / f"{key}.md").stat().st_size > 0 and (out / f"{key}.tex").is_file()


def test_backbones_at_equal_training_time_pair_the_runs_of_a_scene_and_seed(tmp_path):
    # nerf and ngp on two scenes x two seeds; ngp is 1 dB ahead at 60 s on every pair and
    # behind at the end by 0.5 / 1.5 dB; a collapsed hexplane run is counted, not scored
    sweep = tmp_path / "sweep"
    k = 0
    for scene in ("spheres", "lego"):
        for seed in (0, 1):
            base = 20.0 + seed + (scene == "lego")
            for model, at60, end in (("nerf", base, base + 3), ("ngp", base + 1,
                                                                base + 3 - 0.5 - seed)):
                named = {"machine": "CPU A ×2"} if model == "nerf" else {}
                write_run(sweep / str(k), _metrics(scene, model=model, psnr=end, seed=seed,
                                                   **named),
                          _curve([30.0, 59.0, 61.0], [base - 2, at60, 99.0],
                                 ["cheap", "full", "cheap"]))
                k += 1
    write_run(sweep / str(k), _metrics("spheres", model="hexplane", psnr=None, seed=0,
                                       status="collapsed"))
    md = budget_markdown(collect_runs([sweep]), budgets=(10.0, 60.0))
    rows = _parse_md(md.split("| backbone − nerf")[0])["Per backbone, at equal training time"]
    assert rows["nerf"]["scored / runs"] == "4 / 4" and rows["hexplane"]["scored / runs"] == "0 / 1"
    # within 10 s: no evaluation yet; within 60 s: the 59 s row, never the 61 s one
    assert rows["nerf"]["PSNR within 10 s"] == "—"
    # the machines of the scored runs: named in the nerf records, absent from the ngp ones
    assert rows["nerf"]["machines (scored runs)"] == "CPU A ×2 (4)"
    assert rows["ngp"]["machines (scored runs)"] == "not recorded (4)"
    assert rows["hexplane"]["machines (scored runs)"] == "—"
    assert rows["nerf"]["PSNR within 60 s"].startswith("21.00 ± ")
    assert rows["ngp"]["PSNR within 60 s"].startswith("22.00 ± ")
    diff = md.split("| backbone − nerf")[1]
    ngp = next(line for line in diff.splitlines() if line.startswith("| ngp"))
    cells = [c.strip() for c in ngp.strip("|").split("|")]
    assert cells[1] == "—" and cells[2] == "**+1.00 ± 0.00** (4)"
    # end: −0.5 and −1.5 per seed → mean −1.0, t_{0.975,3}·0.577/2 = 0.919
    assert cells[3] == "**-1.00 ± 0.92** (4)"
    assert psnr_within(np.array([3.0, 1.0, 2.0]), np.array([30.0, 10.0, np.nan]), 2.5) == 10.0


def test_missing_and_malformed_runs(tmp_path, caplog):
    bad = tmp_path / "sweep" / "bad"
    bad.mkdir(parents=True)
    (bad / "metrics.json").write_text(json.dumps({"scene": "spheres"}))
    with caplog.at_level("WARNING"):
        paths = build_report([tmp_path / "sweep", tmp_path / "nope"], tmp_path / "out")
    assert any("model: expected present" in r.message for r in caplog.records)
    md = (tmp_path / "out" / "table3.md").read_text()
    ours = [row["PSNR↑ ours"] for g in _parse_md(md).values() for row in g.values()]
    assert ours and set(ours) == {"—"}  # nothing made up
    assert len(paths) == 13  # 5 tables × (md, tex), the figure, its table, the findings


def test_segment_curves_and_null_settings(tmp_path):
    run = write_run(tmp_path / "run", _metrics("rig_lowlight", views=None, fps=None))
    for k, (wall, psnr) in enumerate((([1.0, 2.0], [14.0, 19.0]), ([0.5, 1.5], [21.0, 24.0]))):
        write_curve(run / f"seg{k}" / "curve.csv", _curve(wall, psnr, ["full", "full"]))
    (r,) = collect_runs([tmp_path])
    assert r.views is None and r.fps is None
    s = summarize(r)
    # seg1's clock restarts: shifted by seg0's last time (2 s) → 20 dB first at 2.5 s
    assert s.times[15.0] == 2.0 and s.times[20.0] == 2.5 and s.best_psnr == 24.0
    t6 = next(iter(_parse_md(to_markdown(build_table("table6", [r]))).values()))
    assert t6["all"]["PSNR↑ ours"] == "25.000" and t6["all"]["PSNR↑ paper"] == "—"


def test_copy_runs_keeps_a_regenerable_record(tmp_path):
    sweep = tmp_path / "multirun" / "table3"
    write_run(sweep / "row=full,scene=spheres", _metrics("spheres", psnr=25.5),
              _curve([1.0, 2.0], [20.0, 25.5], ["cheap", "full"]))
    write_run(sweep / "row=ngp,scene=spheres", _metrics("spheres", model="ngp", psnr=21.0))
    record = tmp_path / "docs" / "runs"
    assert main([str(sweep), "--out", str(tmp_path / "out"), "--copy-runs", str(record)]) == 0
    copied = sorted(p.relative_to(record).as_posix() for p in record.rglob("*.*"))
    assert copied == ["table3/row=full,scene=spheres/curve.csv",
                      "table3/row=full,scene=spheres/metrics.json",
                      "table3/row=ngp,scene=spheres/metrics.json"]
    # the record alone regenerates the same table
    assert main([str(record), "--out", str(tmp_path / "again")]) == 0
    assert ((tmp_path / "again" / "table3.md").read_text()
            == (tmp_path / "out" / "table3.md").read_text())


def test_cli_default_out_is_git_ignored_and_leaves_docs_results_alone(tmp_path, monkeypatch):
    import shutil
    import subprocess

    from eventrecon.report.__main__ import DEFAULT_OUT

    repo = Path(__file__).resolve().parents[1]
    monkeypatch.chdir(tmp_path)  # a checkout-like tree: committed results + a local sweep
    committed = tmp_path / "docs" / "results"
    committed.mkdir(parents=True)
    (committed / "table3.md").write_text("committed\n")
    before = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in committed.rglob("*")}
    _sweep(tmp_path, [_metrics("spheres", psnr=27.0)], "table3")

    assert main(["multirun", "outputs"]) == 0  # what `make tables` runs
    out = tmp_path / DEFAULT_OUT
    assert out == tmp_path / "multirun" / "report"
    assert (out / "table3.md").stat().st_size > 0 and (out / "accuracy_vs_time.png").is_file()
    assert {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in committed.rglob("*")} == before
    # the report inside multirun/ is not read back as runs by the next `make tables`
    first = (out / "table3.md").read_text()
    assert main(["multirun", "outputs"]) == 0 and (out / "table3.md").read_text() == first
    # and the project's .gitignore keeps it out of the tree
    git = shutil.which("git")
    if git is None or not (repo / ".git").exists():
        pytest.skip("no git checkout to check .gitignore against")
    written = [p.relative_to(tmp_path).as_posix() for p in out.iterdir()]
    ignored = subprocess.run([git, "-C", str(repo), "check-ignore", "--no-index", *written],
                             capture_output=True, text=True, check=False).stdout.split()
    assert sorted(ignored) == sorted(written)


def test_findings_decide_decay_per_scene_and_full_model_on_the_real_scene(tmp_path):
    from eventrecon.report.findings import check_findings

    jobs = []
    for seed, (d_low, d_noisy) in enumerate([(0.001, 0.020), (-0.001, 0.022), (0.0, 0.018)]):
        for scene, d in (("rig_lowlight", d_low), ("rig_noisy", d_noisy)):
            jobs += [_metrics(scene, psnr=30.0, ssim=0.80 + d, lpips=None, seed=seed,
                              experiment="table4"),
                     _metrics(scene, loss="no_decay", psnr=30.0, ssim=0.80, lpips=None,
                              seed=seed, experiment="table4")]
        # a row better than the full model, but only on the noisy variant: it must not
        # decide the full-model claim, which is about the real-like scene
        jobs.append(_metrics("rig_noisy", loss="no_event", psnr=30.0, ssim=0.95, lpips=None,
                             seed=seed, experiment="table4"))
    runs = collect_runs([_sweep(tmp_path, jobs).parent.parent])
    found = {f.claim: f for f in check_findings(runs)}
    low = found["Event decay improves SSIM/LPIPS on noisy real-like data (Tab. 4, `rig_lowlight`)"]
    noisy = found["Event decay improves SSIM/LPIPS on noisy real-like data (Tab. 4, `rig_noisy`)"]
    assert low.verdict == "inconclusive" and low.diff.n == 3
    assert low.diff.mean == pytest.approx(0.0, abs=1e-12)
    assert noisy.verdict == "holds" and noisy.diff.n == 3
    assert noisy.diff.mean == pytest.approx(0.020) and noisy.diff.low > 0
    assert "LPIPS unavailable" in noisy.note
    full = found["SSIM favours the full model on the real-like scene (Tab. 4)"]
    assert full.verdict == "inconclusive" and "w/o decay" in full.cells


def test_row_differences_pair_the_full_model_with_each_tab3_row(tmp_path):
    from eventrecon.report.findings import row_differences, row_differences_markdown

    jobs = []
    for seed in range(3):
        for scene, offset in (("spheres", 0.0), ("static_lego", 1.0)):
            jobs += [_metrics(scene, psnr=25.0 + offset, seed=seed, experiment="table3"),
                     _metrics(scene, model="ngp", psnr=25.0 + offset - 0.1 * (seed + 1),
                              seed=seed, experiment="table3"),
                     _metrics(scene, loss="no_acc", psnr=22.0, seed=seed, experiment="table3",
                              status="collapsed" if seed == 0 else "ok")]
    runs = collect_runs([_sweep(tmp_path, jobs).parent.parent])
    diffs = {d.row: d for d in row_differences(runs)}
    ngp, no_acc = diffs["NGP"], diffs["w/o L_acc"]
    # NGP: 0.1, 0.2, 0.3 below the full model on both scenes
    assert ngp.all_scenes.n == 6 and ngp.all_scenes.mean == pytest.approx(0.2)
    assert ngp.moving.n == 3 and ngp.moving.mean == pytest.approx(0.2) and ngp.lost == 0
    # w/o L_acc: seed 0 collapsed on both scenes, its pairs dropped; 3 dB (spheres), 4 dB
    assert no_acc.lost == 2 and no_acc.all_scenes.n == 4
    assert no_acc.all_scenes.mean == pytest.approx(3.5) and no_acc.moving.mean == pytest.approx(3.0)
    md = row_differences_markdown(list(diffs.values()))
    assert "| NGP | **0.20 ± " in md and "| w/o L_acc | **3.50 ± " in md


def test_findings_pair_only_runs_of_one_method_version(tmp_path):
    from eventrecon.report.findings import paired
    from eventrecon.report.runs import current_runs
    from eventrecon.results.records import METHOD_VERSION

    new, old = {"method_version": METHOD_VERSION}, {"method_version": None}
    jobs = []
    for seed in range(3):
        # seeds 0, 1: both rows re-run at this version (full 1 dB above w/o L_event);
        # seed 2: the full model re-run, w/o L_event still version 1 and 9 dB lower
        jobs += [_metrics("spheres", psnr=25.0 + seed, seed=seed, experiment="table3", **new),
                 _metrics("spheres", loss="no_event", psnr=(24.0 if seed < 2 else 18.0) + seed,
                          seed=seed, experiment="table3", **(new if seed < 2 else old))]
    runs = current_runs(collect_runs([_sweep(tmp_path, jobs).parent.parent]))
    d, lost = paired(runs, lambda r: r.loss == "full", lambda r: r.loss == "no_event")
    assert (d.n, lost) == (2, 0) and d.mean == pytest.approx(1.0)   # seed 2 is no pair


def test_collapsed_cells_set_each_collapse_beside_the_papers_own_cell(tmp_path):
    from eventrecon.report.collapses import collapsed_cells, collapsed_cells_markdown

    jobs = []
    for seed in range(3):
        # only L_event on the static control: the paper's cell (16.50) is 7.36 dB below its
        # column's best (the full model, 23.863) — the paper fails there too
        jobs.append(_metrics("static_lego", loss="only_event", seed=seed, experiment="table3",
                             status="collapsed" if seed < 2 else "ok"))
        # w/o L_acc on lego: the paper's cell (23.178) is its column's best but 0.0 below
        jobs.append(_metrics("lego", loss="no_acc", seed=seed, experiment="table3",
                             status="collapsed" if seed == 1 else "ok"))
        jobs.append(_metrics("lego", seed=seed, experiment="table3"))  # nothing collapsed
        # Tab. 5 rows are frame rates
        jobs.append(_metrics("rig_lowlight", fps=0.5, seed=seed, experiment="table5",
                             status="collapsed" if seed == 2 else "ok"))
    runs = collect_runs([_sweep(tmp_path, jobs).parent.parent])
    # a later re-run of a seed replaces it: Tab. 5 seed 2, re-run and scored, is no collapse
    rerun = write_run(tmp_path / "rerun" / "0", _metrics("rig_lowlight", fps=0.5, seed=2,
                                                          experiment="table5"))
    newer = max(r.mtime for r in runs) + 10
    os.utime(rerun / "metrics.json", (newer, newer))
    rerun_runs = runs + collect_runs([tmp_path / "rerun"])
    assert ("table5", "0.5", "rig_lowlight") not in {(c.table, c.row, c.scene)
                                                       for c in collapsed_cells(rerun_runs)}
    cells = {(c.table, c.row, c.scene): c for c in collapsed_cells(runs)}
    assert set(cells) == {("table3", "only L_event", "static_lego"),
                          ("table3", "w/o L_acc", "lego"), ("table5", "0.5", "rig_lowlight")}
    static = cells[("table3", "only L_event", "static_lego")]
    assert static.collapsed_seeds == [0, 1] and static.runs == 3
    assert static.paper_psnr == pytest.approx(16.500)
    assert static.paper_gap == pytest.approx(23.863 - 16.500) and static.paper_fails is True
    lego = cells[("table3", "w/o L_acc", "lego")]
    assert lego.collapsed_seeds == [1] and lego.paper_gap == pytest.approx(0.0)
    assert lego.paper_fails is False
    fps = cells[("table5", "0.5", "rig_lowlight")]
    best5 = max(v[0] for (_, col), v in PAPER_TABLES["table5"].values.items() if col == "Sword")
    assert fps.paper_gap == pytest.approx(best5 - PAPER_TABLES["table5"].value("0.5", "Sword")[0])
    md = collapsed_cells_markdown(list(cells.values()))
    assert "| table3 | w/o L_acc | `lego` | 1/3 | 1 | 23.18 | 0.00 | **no** |" in md
    assert "| table3 | only L_event | `static_lego` | 2/3 | 0, 1 | 16.50 | 7.36 | yes |" in md
    assert collapsed_cells_markdown([]) == ""


def test_a_newer_method_version_supersedes_its_job_and_a_mixed_table_says_so(tmp_path):
    from eventrecon.report.runs import current_runs
    from eventrecon.results.records import METHOD_VERSION

    old = {"method_version": None}          # a record older than the field: version 1
    new = {"method_version": METHOD_VERSION, "lr_end_factor": 1.0}   # a key v1 lacked
    jobs = [_metrics("spheres", psnr=20.0, seed=0, **old),
            _metrics("spheres", psnr=30.0, seed=0, **new),   # the same job, re-run
            _metrics("spheres", psnr=26.0, seed=1, **old),   # not re-run yet
            _metrics("lego", psnr=22.0, seed=0, **old)]
    sweep = _sweep(tmp_path, jobs, "table3")
    stale = sweep / "0" / "metrics.json"      # the version-1 record is the later file
    os.utime(stale, (stale.stat().st_mtime + 60, stale.stat().st_mtime + 60))
    runs = collect_runs([sweep.parent.parent])
    kept = current_runs(runs)
    assert sorted((r.scene, r.record["seed"], r.version) for r in kept) == [
        ("lego", 0, 1), ("spheres", 0, METHOD_VERSION), ("spheres", 1, 1)]
    # a cell built from all runs still takes each seed's newest version (30, not 20)
    from eventrecon.report.cells import per_seed
    spheres = per_seed([r for r in runs if r.scene == "spheres"])
    assert [(r.record["seed"], r.metric("psnr")) for r in spheres] == [(0, 30.0), (1, 26.0)]
    md = to_markdown(build_table("table3", kept))
    sph = _parse_md(md)[next(t for t in _parse_md(md) if t.startswith("Spheres"))]
    assert sph["Full Model"]["PSNR↑ ours"].startswith("28.000 ±")   # (30 + 26) / 2, never 20
    from eventrecon.report.runs import versions_markdown
    assert versions_markdown(kept).splitlines()[2] == (
        f"- table3: 2 runs of method version 1, 1 run of method version {METHOD_VERSION}")
    text = " ".join(md.split())
    assert ("Runs of several method versions (records' method_version): 2 of version 1 "
            "(each of a ray's three renders") in text
    assert f"; 1 of version {METHOD_VERSION} (" in text


def test_a_version_that_changed_a_default_supersedes_the_old_default_and_prunes_it(tmp_path):
    from eventrecon.report.runs import current_runs, prune_superseded, supersedes
    from eventrecon.results.records import VERSION_KEYS

    assert VERSION_KEYS[4] == ("betas_power",)
    v3 = {"method_version": 3, "sizing": "cpu_nerf"}
    jobs = [_metrics("rig_lowlight", seed=5, psnr=24.0, **v3),             # 0: betas 1 (old)
            _metrics("rig_lowlight", seed=5, psnr=25.0, method_version=4,  # 1: its re-run
                     sizing="cpu_nerf", betas_power=10.0),
            _metrics("rig_lowlight", seed=6, psnr=24.5, **v3),             # 2: not re-run
            _metrics("rig_lowlight", seed=5, psnr=23.0, lr_warmup=50, **v3),  # 3: other job
            _metrics("rig_lowlight", model="ngp", seed=5, method_version=3,   # 4: stands for 4
                     sizing="cpu_ngp")]
    sweep = _sweep(tmp_path, jobs, "table4")
    runs = {r.path.name: r for r in collect_runs([sweep])}
    assert supersedes(runs["1"], runs["0"]) and not supersedes(runs["0"], runs["1"])
    assert not supersedes(runs["1"], runs["2"]) and not supersedes(runs["1"], runs["3"])
    assert sorted(r.path.name for r in current_runs(runs.values())) == ["1", "2", "3", "4"]
    # a committed copy loses the superseded record only; the others stay byte for byte
    before = {p: p.read_bytes() for p in sweep.rglob("*.json") if p.parent.name != "0"}
    assert prune_superseded(sweep) == [sweep / "0"]
    assert not (sweep / "0" / "metrics.json").exists()
    assert {p: p.read_bytes() for p in sweep.rglob("*.json")} == before


def test_a_version_that_changed_only_some_runs_leaves_the_others_current(tmp_path,
                                                                          monkeypatch):
    from eventrecon.results import records

    monkeypatch.setattr(records, "METHOD_VERSION", 4)   # version 4's scope, at any later one
    changed = records.VERSION_SCOPE[4]
    assert [s for s in ("cpu_nerf", "cpu_ngp", "cpu_hexplane", "cpu_tensorf_cp", "paper_nerf",
                        "paper_ngp", "gpu_ngp") if changed(s)] == ["cpu_nerf", "paper_ngp",
                                                                    "gpu_ngp"]
    base = {"scene": "spheres", "model": "hexplane", "loss": "full", "views": 6, "fps": 5.0,
            "status": "ok", "psnr": 25.0, "max_steps": 1000, "method_version": 3}
    found = {}
    for name, sizing in (("hexplane", "cpu_hexplane"), ("nerf", "cpu_nerf"),
                         ("paper_ngp", "paper_ngp"), ("unnamed", None)):
        path = records.write_metrics(tmp_path / name, {**base, "sizing": sizing})
        found[name] = (records.record_version(records.read_metrics(path)),
                       records.finished_metrics(path, 1000, evaluate=True) is not None)
    # version 4 changed the CPU NeRF (betas^10) and NGP at the paper's size (the authors'
    # betas): a version-3 CPU HexPlane record trains the same and stays finished; the others,
    # and a record that says no sizing outside a job, train again
    assert found == {"hexplane": (4, True), "nerf": (3, False), "paper_ngp": (3, False),
                     "unnamed": (3, False)}
    assert records.record_version({"method_version": 2, "sizing": "cpu_hexplane"}) == 2
    # a pair compares runs that trained as one version: the version-3 HexPlane record (it
    # stands for 3 and 4) pairs with a version-3 and a version-4 NeRF; those two do not pair
    from eventrecon.report.pairs import paired
    nerf = {"sizing": "cpu_nerf"}
    jobs = [_metrics("spheres", model="hexplane", psnr=25.0, seed=0, method_version=3,
                     sizing="cpu_hexplane"),
            _metrics("spheres", psnr=24.0, seed=0, method_version=3, **nerf),
            _metrics("spheres", loss="no_event", psnr=22.0, seed=0, method_version=4, **nerf)]
    runs = collect_runs([_sweep(tmp_path / "pairs", jobs, "table3").parent.parent])
    full, hexplane = (lambda r: r.model == "nerf" and r.loss == "full"), (
        lambda r: r.model == "hexplane")
    no_event = lambda r: r.loss == "no_event"  # noqa: E731
    assert [paired(runs, hexplane, b)[0].mean for b in (full, no_event)] == [1.0, 3.0]
    assert paired(runs, full, no_event)[0] is None
    # a segment's done.json (or checkpoint) of version 3 names no sizing: it is the running
    # job's, so a CPU HexPlane job keeps its trained segment and a CPU NeRF job trains again
    records.write_done(tmp_path / "seg0", 1000, 1000, 10.0, 0, data_id="d")
    done = json.loads((tmp_path / "seg0" / "done.json").read_text())
    (tmp_path / "seg0" / "done.json").write_text(json.dumps(
        {k: v for k, v in done.items() if k != "sizing"} | {"method_version": 3}))
    for sizing, kept in (("cpu_hexplane", True), ("cpu_nerf", False)):
        monkeypatch.setattr(records, "sizing_choice", lambda s=sizing: s)
        assert (records.read_done(tmp_path / "seg0", 1000, current_method=True,
                                  data_id="d") is not None) == kept


def test_version_5_retrains_the_cpu_hexplane_runs_only(tmp_path, monkeypatch):
    from eventrecon.results import records

    monkeypatch.setattr(records, "METHOD_VERSION", 5)
    assert [s for s in ("cpu_nerf", "cpu_ngp", "cpu_hexplane", "cpu_tensorf_cp", "paper_nerf",
                        "gpu_hexplane") if records.VERSION_SCOPE[5](s)] == ["cpu_hexplane"]
    base = {"scene": "spheres", "model": "hexplane", "loss": "full", "views": 6, "fps": 5.0,
            "status": "ok", "psnr": 25.0, "max_steps": 1000, "method_version": 4}
    found = {}
    for sizing in ("cpu_hexplane", "cpu_tensorf_cp", "paper_hexplane"):
        path = records.write_metrics(tmp_path / sizing, {**base, "sizing": sizing})
        found[sizing] = (records.record_version(records.read_metrics(path)),
                         records.finished_metrics(path, 1000, evaluate=True) is not None)
    # the CPU HexPlane's grid changed size (128 -> 48): its version-4 record is stale and
    # its job trains again; the other sizings train as before and keep their records
    assert found == {"cpu_hexplane": (4, False), "cpu_tensorf_cp": (5, True),
                     "paper_hexplane": (5, True)}


def test_a_table_whose_runs_of_a_scene_used_different_datasets_says_so(tmp_path):
    from eventrecon.report.cells import method_notes
    from eventrecon.report.runs import read_run

    def runs(*ids):
        sweep = _sweep(tmp_path / "-".join(map(str, ids)),
                       [_metrics("spheres", seed=i, data_id=d) for i, d in enumerate(ids)])
        return [read_run(sweep / str(i)) for i in range(len(ids))]
    assert not any("datasets" in n for n in method_notes(runs("spheres-aa", "spheres-aa")))
    note = next(n for n in method_notes(runs("spheres-aa", "spheres-bb", "spheres-bb", None))
                if "datasets" in n)
    assert note == ("`spheres` runs on several datasets (records' data_id): 1 on `spheres-aa`; "
                    "2 on `spheres-bb`; 1 unrecorded (made before records named their data). "
                    "Cells are not yet all re-run on one.")


def test_pairs_to_resolve_is_the_smallest_n_whose_interval_is_narrow_enough():
    from scipy.stats import t as student

    from eventrecon.report.stats import MeanCI, mean_ci, pairs_to_resolve

    for values, effect in (([0.1, 0.5, -0.2, 0.3], 0.25), ([1.0, 2.0], 3.0),
                           ([0.0, 1.0, 0.0, 1.0, 0.5], 0.05), ([2.0, 2.0, 2.0], 0.1)):
        d = mean_ci(values)
        sd = float(np.std(values, ddof=1))
        brute = next(n for n in range(2, 10**6)
                     if student.ppf(0.975, n - 1) * sd / math.sqrt(n) < abs(effect))
        assert pairs_to_resolve(d, effect) == brute
        assert pairs_to_resolve(d, -effect) == brute          # only |effect| matters
    assert pairs_to_resolve(mean_ci([1.0]), 0.5) is None      # no spread from one value
    assert pairs_to_resolve(mean_ci([0.0, 1.0]), 0.0) is None
    assert pairs_to_resolve(mean_ci([0.0, 1.0]), 1e-6, limit=1000) is None
    assert pairs_to_resolve(MeanCI(0.0, 0.0, 3), 0.1) == 2    # no spread at all


def test_findings_set_the_papers_difference_beside_ours(tmp_path):
    from eventrecon.report.findings import (
        check_findings,
        row_differences,
        row_differences_markdown,
    )
    from eventrecon.report.stats import pairs_to_resolve

    jobs = []
    for seed in range(4):
        for scene in ("spheres", "static_lego"):
            jobs += [_metrics(scene, psnr=25.0, seed=seed, experiment="table3"),
                     _metrics(scene, model="ngp", psnr=25.0 - 0.1 * (seed + 1), seed=seed,
                              experiment="table3"),
                     # w/o L_sparsity: ±1 dB around the full model, no effect on average
                     _metrics(scene, loss="no_sparsity", psnr=25.0 + (-1) ** seed, seed=seed,
                              experiment="table3")]
            if scene == "spheres":
                jobs.append(_metrics(scene, loss="no_event", psnr=24.0 - 0.1 * seed, seed=seed,
                                     experiment="table3"))
    runs = collect_runs([_sweep(tmp_path, jobs).parent.parent])
    diffs = {d.row: d for d in row_differences(runs)}
    paper3 = PAPER_TABLES["table3"]
    # the paper's Full − NGP on the columns of our two scenes, Spheres and Static Lego
    want = sum(paper3.value("Full Model", c)[0] - paper3.value("NGP", c)[0]
               for c in ("Spheres", "Static Lego")) / 2
    ngp = diffs["NGP"]
    assert ngp.paper == pytest.approx(want) and want == pytest.approx(4.6915)
    assert ngp.all_scenes.mean == pytest.approx(0.25) and ngp.needed == 2
    sparsity = diffs["w/o L_sparsity"]
    assert sparsity.paper == pytest.approx((29.765 - 29.358 + 23.863 - 23.698) / 2)
    assert sparsity.needed == pairs_to_resolve(sparsity.all_scenes, sparsity.paper)
    assert sparsity.needed > sparsity.all_scenes.n     # ±1 dB spread hides a 0.29 dB effect
    md = row_differences_markdown(list(diffs.values()))
    assert "| NGP | **0.25 ± " in md and "| 4.69 | **no** | met |" in md
    assert f"| 0.29 | yes | {sparsity.needed} |" in md
    found = {f.claim: f for f in check_findings(runs)}
    event = found["Removing L_event hurts on scenes with events (Tab. 3)"]
    # only spheres has w/o L_event and motion: the paper's Spheres cells
    assert event.paper == pytest.approx(29.765 - 27.744) and event.diff.n == 4
    best = found["Full model best on average (Tab. 3)"]
    # the closest row (w/o L_sparsity, mean 0) decides; the paper's difference is its own
    assert "w/o L_sparsity" in best.cells and best.paper == pytest.approx(sparsity.paper)
    assert best.needed == sparsity.needed


def test_a_paper_cell_that_repeats_another_rows_is_named_with_the_difference_without_it(
        tmp_path):
    """The paper's Blender cell of w/o L_event equals w/o clipping's in all three metrics:
    the L_event comparison on blender + spheres keeps the printed difference and says what
    it is without that column (the Spheres cells alone); rows without a repeated cell
    carry no note."""
    from eventrecon.report.findings import (
        check_findings,
        row_differences,
        row_differences_markdown,
    )

    t3 = PAPER_TABLES["table3"]
    assert t3.repeated("w/o L_event", "Blender") == "w/o clipping"
    assert t3.repeated("w/o clipping", "Blender") == "w/o L_event"
    assert t3.repeated("w/o L_event", "Spheres") is None
    assert t3.repeated("w/o L_event", "Average") is None       # a mean, not a measurement
    jobs = []
    for seed in range(3):
        for scene in ("blender", "spheres"):
            jobs += [_metrics(scene, psnr=25.0, seed=seed, experiment="table3"),
                     _metrics(scene, loss="no_event", psnr=24.0 - 0.1 * seed, seed=seed,
                              experiment="table3"),
                     _metrics(scene, model="ngp", psnr=24.5, seed=seed, experiment="table3")]
    runs = collect_runs([_sweep(tmp_path, jobs).parent.parent])
    event = {f.claim: f for f in check_findings(runs)}[
        "Removing L_event hurts on scenes with events (Tab. 3)"]
    printed = sum(t3.value("Full Model", c)[0] - t3.value("w/o L_event", c)[0]
                  for c in ("Blender", "Spheres")) / 2
    assert event.paper == pytest.approx(printed) and printed == pytest.approx(4.7465)
    spheres_only = 29.765 - 27.744
    assert "(Blender `w/o L_event` = `w/o clipping`)" in event.note
    assert f"difference is {spheres_only:.2f} (inside ours: no)" in event.note
    diffs = {d.row: d for d in row_differences(runs)}
    assert diffs["NGP"].note == "" and "without it" in diffs["w/o L_event"].note
    md = row_differences_markdown(list(diffs.values()))
    assert "- w/o L_event: the paper repeats a cell" in md and "- NGP:" not in md


def test_full_model_best_waits_for_rows_without_pairs_of_one_version(tmp_path):
    """A table partly re-run at a new method version: the full model beats the one row
    re-run with it, but a row still at the old version has no pairs and must not let the
    claim hold."""
    from eventrecon.report.findings import check_findings
    from eventrecon.report.runs import current_runs
    from eventrecon.results.records import METHOD_VERSION

    new, old = {"method_version": METHOD_VERSION}, {"method_version": None}
    jobs = []
    for seed in range(3):
        jobs += [_metrics("spheres", psnr=25.0, seed=seed, experiment="table3", **new),
                 _metrics("spheres", loss="no_event", psnr=24.0 - 0.1 * seed, seed=seed,
                          experiment="table3", **new),
                 _metrics("spheres", model="ngp", psnr=30.0, seed=seed, experiment="table3",
                          **old)]
    runs = current_runs(collect_runs([_sweep(tmp_path, jobs).parent.parent]))
    best = {f.claim: f for f in check_findings(runs)}["Full model best on average (Tab. 3)"]
    assert best.verdict == "inconclusive" and best.diff.mean == pytest.approx(1.1)
    assert "1 row(s) without scored pairs of one method version" in best.note


def test_sweep_costs_sum_the_current_versions_job_times_and_price_the_older_runs(tmp_path):
    from eventrecon.report.compute import sweep_costs, sweep_costs_markdown
    from eventrecon.report.runs import current_runs
    from eventrecon.results.records import METHOD_VERSION

    v = {"method_version": METHOD_VERSION}
    t3 = [_metrics("spheres", seed=0, total_s=120.0, **v),
          _metrics("lego", seed=0, total_s=300.0, **v),
          _metrics("dress", seed=0, total_s=600.0, **v),   # NeRF: median 300 s
          _metrics("dress", model="ngp", seed=0, total_s=60.0, **v),  # all: median 210 s
          _metrics("blender", seed=0, total_s=90.0),        # version 1: owed at 300 s,
          _metrics("blender", seed=1, total_s=90.0)]        # its sweep's NeRF median
    t7 = [_metrics("spheres", views=2, seed=0, total_s=200.0),   # only older runs: NeRF's
          _metrics("spheres", views=3, seed=0, total_s=400.0),   # median in any sweep (300)
          _metrics("spheres", model="ngp", seed=0, total_s=10.0),        # NGP's (60)
          _metrics("spheres", model="hexplane", seed=0, total_s=500.0),  # no current
          _metrics("spheres", model="hexplane", seed=1, total_s=700.0)]  # one: own (600)
    runs = current_runs(collect_runs([_sweep(tmp_path / "a", t3, "table3").parent.parent,
                                      _sweep(tmp_path / "b", t7, "table7").parent.parent]))
    c3, c7 = sweep_costs(runs)
    assert (c3.experiment, c3.runs, c3.median_s, c3.total_s, c3.stale) == (
        "table3", 4, 210.0, 1080.0, 2)
    assert c3.wall_s == pytest.approx(540.0) and c3.owed_s == pytest.approx(2 * 300.0 / 2)
    assert (c7.runs, c7.total_s, c7.stale) == (0, 0.0, 5) and math.isnan(c7.median_s)
    assert c7.owed_s == pytest.approx((2 * 300.0 + 60.0 + 2 * 600.0) / 2)
    md = sweep_costs_markdown([c3, c7])
    assert "| `table3` | 4 | 3.5 | 0.30 | 0.15 | 2 | 0.08 |" in md
    assert "| `table7` | 0 | — | 0.00 | 0.00 | 5 | 0.26 |" in md
    assert "| all | 4 |  | 0.30 | 0.15 | 7 | 0.34 |" in md
    assert sweep_costs_markdown([]) == ""
    # a record without total_s counts its training time
    old = _metrics("spheres", seed=0, **v)
    c = sweep_costs(collect_runs([_sweep(tmp_path / "c", [old], "table3").parent.parent]))[0]
    assert c.total_s == 100.0


def test_time_to_level_on_the_median_of_the_last_points_ignores_a_lone_spike():
    # a curve at 24 dB with one point spiking to 27 and then rising to 26 for good: the
    # raw first crossing of 25.5 is the spike (t = 3); the median of the last three
    # points reaches it only once two of three are above (t = 7); NaN points are ignored
    w = np.arange(1.0, 9.0)
    p = np.array([24.0, 24.1, 27.0, 24.0, 24.2, 26.0, 26.1, np.nan])
    assert time_to_level(w, p, 25.5) == 3.0
    assert time_to_level(w, p, 25.5, window=3) == 7.0
    assert time_to_level(w, p, 26.5, window=3) is None
    np.testing.assert_array_equal(trailing_median(p[:7], 3),
                                  [24.0, 24.05, 24.1, 24.1, 24.2, 24.2, 26.0])


def test_a_report_of_folders_that_do_not_exist_writes_nothing(tmp_path, caplog):
    out = tmp_path / "docs" / "results"
    out.mkdir(parents=True)
    (out / "table3.md").write_text("committed\n")
    with caplog.at_level("ERROR"):
        assert main([str(tmp_path / "multirn"), "--out", str(out)]) == 2   # a typo
    assert [r.getMessage() for r in caplog.records if r.levelname == "ERROR"] == [
        f"{tmp_path / 'multirn'}: run folders: expected at least one existing folder of runs "
        "(make some with python train.py -m experiment=table3 scale=cpu; the committed "
        "records: python -m eventrecon.report docs/results/runs), got no such folder"]
    assert sorted(p.name for p in out.iterdir()) == ["table3.md"]
    assert (out / "table3.md").read_text() == "committed\n"
