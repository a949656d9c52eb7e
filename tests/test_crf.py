"""CRF calibration: recovery of ε from a simulated sweep, bias of the image average."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest

from eventrecon.capture.crf import (
    average_fit_bias,
    exposure_from_name,
    fit_crf,
    load_sweep_csv,
    simulate_sweep,
)
from eventrecon.capture.crf_model import apply_crf
from eventrecon.rig import main

EXPOSURES = np.linspace(0.02, 1.6, 40)


def test_exact_on_noise_free_lines():
    v, slopes = simulate_sweep(EXPOSURES, 300, eps=3e-2, noise=0.0, rng=np.random.default_rng(0))
    fit = fit_crf(EXPOSURES, v)
    assert abs(fit.eps - 3e-2) < 1e-12
    np.testing.assert_allclose(fit.gain, slopes, rtol=1e-10)
    np.testing.assert_allclose(fit.eps_per_pixel, 3e-2, atol=1e-10)
    assert fit.residual < 1e-12


def test_joint_fit_matches_generic_least_squares():
    """Closed form == np.linalg.lstsq on the design [one column per pixel slope, −1]."""
    rng = np.random.default_rng(1)
    v, _ = simulate_sweep(EXPOSURES, 20, noise=1e-2, rng=rng)
    fit = fit_crf(EXPOSURES, v)
    k, j = np.nonzero(fit.used)
    A = np.zeros((len(k), 21))
    A[np.arange(len(k)), j] = EXPOSURES[k]
    A[:, -1] = -1.0
    sol = np.linalg.lstsq(A, v[k, j], rcond=None)[0]
    assert abs(sol[-1] - fit.eps) < 1e-12
    np.testing.assert_allclose(sol[:-1], fit.gain, rtol=1e-10)


@pytest.mark.parametrize("seed", range(5))
def test_recovers_eps_with_noise_vignetting_and_8bit(seed):
    v, _ = simulate_sweep(EXPOSURES, 256, eps=3e-2, noise=4e-3, vignetting=0.5,
                          rng=np.random.default_rng(seed))
    v = np.round(v * 255) / 255  # 8-bit frames
    single, average = average_fit_bias(EXPOSURES, v)
    assert abs(single - 3e-2) < 2e-3
    # the image average mixes clipped and unclipped pixels: its line is far off
    assert abs(average - 3e-2) > 2e-2


@pytest.mark.parametrize("seed", range(3))
def test_recovers_eps_from_the_simulators_own_frame_effects(seed):
    """The sweep made by the simulator's frame pipeline (conf names, as a scene lists
    them): flat light × exposure → vignetting → low-light photon + read noise → crf
    (ε = 3e-2) → 8-bit ADC. Calibration on single pixels recovers ε within 2e-3."""
    from eventrecon.sim.config import effect_rng
    from eventrecon.sim.frame_effects import FRAME_EFFECTS, FrameContext

    H, W = 24, 32
    effects = FRAME_EFFECTS.build([
        {"name": "vignetting", "strength": 0.5},
        {"name": "low_light", "photons": 20000.0, "read_noise": 2e-3},
        {"name": "crf", "eps": 3e-2},
        {"name": "quantize_8bit"},
    ], "crf sweep")
    K = np.array([[30.0, 0, (W - 1) / 2], [0, 30.0, (H - 1) / 2], [0, 0, 1]])
    ctx = FrameContext(render=lambda t: np.zeros((len(t), H, W)), t=0.5, duration_s=1.0, K=K)
    frames = []
    for k, e in enumerate(EXPOSURES):
        img = np.full((H, W), 0.8 * e)  # constant light: irradiance ∝ exposure time
        for fx in effects:
            img = fx.apply(img, ctx, effect_rng(seed, "frames", fx.name, fx.occurrence, k))
        frames.append(img.reshape(-1))
    fit = fit_crf(EXPOSURES, np.stack(frames))
    assert abs(fit.eps - 3e-2) < 2e-3
    # the vignetting shows as per-pixel slopes from 0.8 (centre) down to 0.4 (corners)
    assert 0.38 < np.nanmin(fit.gain) < 0.45 and 0.78 < np.nanmax(fit.gain) < 0.82


def test_saturated_and_zero_samples_are_excluded():
    v = apply_crf(np.outer(EXPOSURES, [0.9, 1.5]), 3e-2)
    fit = fit_crf(EXPOSURES, v)
    assert not fit.used[v >= 0.95].any() and not fit.used[v <= 0.02].any()
    assert fit.used.sum() == ((v > 0.02) & (v < 0.95)).sum()


def test_exposure_from_file_name():
    from pathlib import Path
    assert exposure_from_name(Path("cam0_exp_2.5ms.png")) == 2.5
    assert exposure_from_name(Path("1000.png")) == 1000.0


def test_cli_on_csv_and_images(tmp_path, capsys):
    v, _ = simulate_sweep(EXPOSURES, 64, noise=2e-3, rng=np.random.default_rng(3))
    rows = np.column_stack([EXPOSURES * 1000, np.round(v * 255)])  # µs, 0..255
    np.savetxt(tmp_path / "sweep.csv", rows, delimiter=",", header="exposure_us,values",
               comments="")
    assert main(["calibrate-crf", "--csv", str(tmp_path / "sweep.csv"),
                 "--plot", str(tmp_path / "fig9.png")]) == 0
    out = capsys.readouterr().out
    eps = float(out.split("eps = ")[1].split()[0])
    assert abs(eps - 3e-2) < 2e-3
    assert iio.imread(tmp_path / "fig9.png").shape[:2] == (400, 600)
    e_csv, v_csv = load_sweep_csv(tmp_path / "sweep.csv")
    assert v_csv.max() <= 1.0 and e_csv[0] == pytest.approx(20.0)

    # images: a vignetted flat field, one PNG per exposure
    h, w = 40, 60
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - w / 2) / (w / 2)) ** 2 + ((yy - h / 2) / (h / 2)) ** 2
    vig = 1 - 0.3 * r2
    rng = np.random.default_rng(4)
    (tmp_path / "imgs").mkdir()
    for e in EXPOSURES[::2]:
        img = apply_crf(e * vig, 3e-2) + 3e-3 * rng.standard_normal((h, w))
        iio.imwrite(tmp_path / "imgs" / f"exp_{e * 1000:.1f}us.png",
                    np.round(np.clip(img, 0, 1) * 255).astype(np.uint8))
    assert main(["calibrate-crf", "--images", str(tmp_path / "imgs"), "--pixels", "100",
                 "--plot", str(tmp_path / "fig9b.png")]) == 0
    eps = float(capsys.readouterr().out.split("eps = ")[1].split()[0])
    assert abs(eps - 3e-2) < 2e-3


def test_cli_bad_csv_is_one_line(tmp_path, capsys):
    (tmp_path / "bad.csv").write_text("1,2,3\n4,5\n")
    assert main(["calibrate-crf", "--csv", str(tmp_path / "bad.csv")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bad.csv: rows: expected equal-length rows" in err
