"""The zoo benchmark's time to the reference PSNR (issue 12's ⅓-of-the-time target)."""

from __future__ import annotations

from benchmarks.bench_zoo import markdown, reference_time

#: A zoo result row but for its backbone, skip mode and curve.
_ROW = {"status": "ok", "steps": 3, "samples_per_ray": 40.0, "real_s": 0.1, "field_s": 0.05,
        "optim_s": 0.01, "rest_s": 0.04, "update_s_per_step": 0.0, "render_s": 2.0,
        "render_samples_per_px": 40.0, "psnr@10": 25.0}


def _curve(wall, psnr, every=500):
    return {"wall_s": list(wall), "step": [every * (i + 1) for i in range(len(wall))],
            "psnr": list(psnr)}


def test_reference_time_reads_both_curves_as_medians_of_their_last_points():
    # none: steps 500, 1000, 1500 at 10, 20, 30 s; its PSNR at step 1000 is the median of
    # (22, 25) = 23.5. grid reaches a trailing median of 23.5 at its third point (median of
    # 21, 24, 23.5 = 23.5), 24 s: 1.2× none's time
    none = _curve([10.0, 20.0, 30.0], [22.0, 25.0, 26.0])
    grid = _curve([8.0, 16.0, 24.0, 32.0], [21.0, 24.0, 23.5, 27.0])
    ref = reference_time(none, grid, 1000)
    assert ref == {"psnr": 23.5, "none_s": 20.0, "grid_s": 24.0}
    short = _curve([10.0], [22.0])                 # none never got to step 1000
    assert reference_time(short, grid, 1000) == {"psnr": None, "none_s": None, "grid_s": None}
    flat = _curve([8.0, 16.0], [20.0, 21.0])       # grid never reaches it
    assert reference_time(none, flat, 1000)["grid_s"] is None


def test_the_zoo_table_gives_the_grid_over_none_time_ratio():
    rows = [{**_ROW, "backbone": "nerf", "skip": "none",
             "curve": _curve([10.0, 20.0, 30.0], [22.0, 25.0, 26.0])},
            {**_ROW, "backbone": "nerf", "skip": "grid",
             "curve": _curve([8.0, 16.0, 24.0, 32.0], [21.0, 24.0, 23.5, 27.0])}]
    table = markdown(rows, [10.0], {"device": "cpu"}, ref_step=1000)
    line = next(x for x in table.splitlines() if x.startswith("| nerf | 23.50"))
    assert [c.strip() for c in line.strip("|").split("|")] == ["nerf", "23.50", "20", "24",
                                                                "1.20"]


def test_a_row_without_a_curve_gives_dashes_not_an_error():
    rows = [{**_ROW, "backbone": "ngp", "skip": s} for s in ("none", "grid")]
    line = next(x for x in markdown(rows, [], {}).splitlines() if x.startswith("| ngp | —"))
    assert [c.strip() for c in line.strip("|").split("|")] == ["ngp", "—", "—", "—", "—"]


def test_one_skip_mode_gives_the_results_table_without_empty_comparisons():
    rows = [{**_ROW, "backbone": name, "skip": "grid"} for name in ("nerf", "ngp")]
    table = markdown(rows, [10.0], {"device": "cpu"})
    assert "Ratios none / grid" not in table and "Time to `skip=none`" not in table
    assert sum(x.startswith(("| nerf | grid", "| ngp | grid")) for x in table.splitlines()) == 2
    assert table.splitlines()[-1] == "Settings: device=cpu"
