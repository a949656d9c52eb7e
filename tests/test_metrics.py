"""PSNR / SSIM / colour correction: known answers and an independent SSIM reference."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from numpy.lib.stride_tricks import sliding_window_view

from eventrecon.common.errors import InputError
from eventrecon.evaluation.metrics import color_correct, evaluate_images, psnr, ssim


def test_psnr_known_answers():
    gt = np.full((10, 12, 3), 0.5)
    assert psnr(gt + 0.1, gt) == pytest.approx(20.0, abs=1e-9)
    assert psnr(gt - 0.01, gt) == pytest.approx(40.0, abs=1e-9)
    assert psnr(gt, gt) == float("inf")
    # half the pixels off by 0.2: MSE = 0.02 → 16.9897 dB
    pred = gt.copy()
    pred[:5] += 0.2
    assert psnr(pred, gt) == pytest.approx(-10 * np.log10(0.02), abs=1e-9)
    # a batch averages the per-frame PSNRs (20 and 40 dB → 30)
    batch = np.stack([gt + 0.1, gt + 0.01])
    assert psnr(batch, np.stack([gt, gt])) == pytest.approx(30.0, abs=1e-9)


def test_torch_and_numpy_agree():
    rng = np.random.default_rng(1)
    a, b = rng.random((2, 16, 16, 3)), rng.random((2, 16, 16, 3))
    assert psnr(torch.tensor(a), torch.tensor(b)) == pytest.approx(psnr(a, b), abs=1e-9)
    assert ssim(torch.tensor(a), torch.tensor(b)) == pytest.approx(ssim(a, b), abs=1e-9)


def _ssim_reference(x: np.ndarray, y: np.ndarray, win: int = 7) -> float:
    """Wang et al. SSIM with a 7×7 uniform window, sample covariances, K=(0.01, 0.03),
    L=1, averaged over valid windows and channels (independent of scikit-image)."""
    c1, c2 = 0.01**2, 0.03**2
    n = win * win
    vals = []
    for c in range(x.shape[-1]):
        wx = sliding_window_view(x[..., c], (win, win))
        wy = sliding_window_view(y[..., c], (win, win))
        mx, my = wx.mean(axis=(-1, -2)), wy.mean(axis=(-1, -2))
        vx = ((wx - mx[..., None, None]) ** 2).sum(axis=(-1, -2)) / (n - 1)
        vy = ((wy - my[..., None, None]) ** 2).sum(axis=(-1, -2)) / (n - 1)
        cxy = ((wx - mx[..., None, None]) * (wy - my[..., None, None])).sum(axis=(-1, -2)) / (
            n - 1
        )
        s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
        vals.append(s.mean())
    return float(np.mean(vals))


def test_ssim_identical_constant_and_reference():
    rng = np.random.default_rng(0)
    img = rng.random((24, 20, 3))
    assert ssim(img, img) == pytest.approx(1.0, abs=1e-12)
    # two flat images: SSIM = (2ab + C1) / (a² + b² + C1), the structure term is 1
    a, b = 0.5, 0.6
    want = (2 * a * b + 1e-4) / (a * a + b * b + 1e-4)
    assert ssim(np.full((16, 16, 3), a), np.full((16, 16, 3), b)) == pytest.approx(want, abs=1e-9)
    # a noisy, blurred degradation against the independent implementation
    noisy = np.clip(img + rng.normal(0, 0.1, img.shape), 0, 1)
    got = ssim(noisy, img)
    assert 0.2 < got < 0.95
    assert got == pytest.approx(_ssim_reference(noisy, img), abs=1e-9)


def test_color_correct_recovers_log_affine_distortion():
    rng = np.random.default_rng(3)
    eps = 1e-2
    gt = rng.uniform(0.1, 0.9, (2, 16, 16, 3))
    a = np.array([0.8, 1.2, 0.9])
    b = np.array([0.05, -0.1, 0.02])
    # gt = exp(a·log(pred+eps) + b) - eps  ⇔  pred = exp((log(gt+eps) - b)/a) - eps
    pred = np.exp((np.log(gt + eps) - b) / a) - eps
    assert 0 < pred.min() and pred.max() < 1  # a valid image
    assert psnr(pred, gt) < 30
    fixed = color_correct(pred, gt, eps=eps)
    assert psnr(fixed, gt) > 120
    out = evaluate_images(pred, gt, lpips=False, color_correct=True)
    assert out["psnr"] > 120 and out["color_corrected"] == "per_image"
    assert out["ssim"] == pytest.approx(1.0, abs=1e-9)
    # off by default: the raw PSNR is reported
    assert evaluate_images(pred, gt, lpips=False)["psnr"] == pytest.approx(psnr(pred, gt))


def test_joint_correction_is_one_fit_in_log_linear_space_over_all_images():
    """EventNeRF's correction undoes one tone curve shared by all images exactly, but not
    a different curve per image (which the per-image fit undoes)."""
    rng = np.random.default_rng(4)
    gt = rng.uniform(0.2, 0.9, (3, 16, 16, 3))
    a, b = np.array([1.05, 1.1, 0.97]), np.array([-0.02, 0.03, 0.01])
    v = np.log(gt ** 2.2 + 0.1)                        # gt's log-linear values
    lin = np.exp((v - b) / a) - 0.1                    # so that a·log(lin + 0.1) + b = v
    assert 0 < lin.min() and lin.max() < 1
    pred = lin ** (1 / 2.2)
    assert psnr(pred, gt) < 35
    out = evaluate_images(pred, gt, lpips=False, color_correct="eventnerf")
    assert out["psnr"] > 100 and out["color_corrected"] == "eventnerf"
    # per-image curves: the joint fit leaves an error, the per-image one (in its space) less
    scale = np.array([0.7, 1.0, 1.4])[:, None, None, None]
    each = np.clip(pred * scale, 0, 1)
    joint = evaluate_images(each, gt, lpips=False, color_correct="eventnerf")["psnr"]
    per = evaluate_images(each, gt, lpips=False, color_correct="per_image")["psnr"]
    assert joint < 40 and per > joint
    with pytest.raises(InputError, match="color_correct"):
        evaluate_images(pred, gt, lpips=False, color_correct="joint")


def test_bad_shapes_raise_input_error():
    with pytest.raises(InputError, match="shape"):
        psnr(np.zeros((4, 4)), np.zeros((4, 4)))
    with pytest.raises(InputError, match="equal to gt"):
        evaluate_images(np.zeros((4, 4, 3)), np.zeros((5, 4, 3)), lpips=False)
