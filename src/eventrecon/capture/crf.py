"""Calibration of the linear camera response with a vertical offset (supplementary Sec. 8).

Setup: a constant light source, an exposure sweep ``e_1 … e_K``; the light reaching
pixel ``j`` is proportional to the exposure, so where the pixel is neither clipped at 0
nor in the saturation roll-off its value is a line (model of
:mod:`eventrecon.capture.crf_model`)

.. math:: v_{kj} = a_j\\, e_k - \\varepsilon ,

with a per-pixel slope ``a_j`` (gain × light × vignetting) and **one** offset ``ε``
shared by all pixels (a property of the sensor's read-out, 3e-2 on the real rig).

Fit (:func:`fit_crf`): joint least squares over the used samples of all pixels,

.. math:: \\min_{a, \\varepsilon} \\sum_{(k, j)\\ \\mathrm{used}}
   (a_j e_k - \\varepsilon - v_{kj})^2 .

For fixed ``ε`` each slope is ``a_j = (B_j + ε C_j)/S_j`` (``S_j = Σ e²``, ``C_j = Σ e``,
``B_j = Σ e v``, ``V_j = Σ v``, ``n_j`` = count, sums over pixel ``j``'s used samples);
substituting gives the closed form

.. math:: \\varepsilon = \\frac{\\sum_j (V_j - B_j C_j / S_j)}{\\sum_j (C_j^2/S_j - n_j)} .

Why joint rather than per-pixel intercepts then a median: it is the maximum-likelihood
estimate under i.i.d. Gaussian noise and uses every sample for the one shared
parameter; the per-pixel intercepts (``CRFFit.eps_per_pixel``) remain as a diagnostic
(their spread shows whether ``ε`` really is shared). Single pixels, not image averages:
under vignetting the average of clipped lines bends (dark corners still at 0 while the
centre rises; the centre saturating while the average is still below the threshold),
so a line through the average is biased (:func:`average_fit_bias` shows it).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eventrecon.capture.crf_model import apply_crf
from eventrecon.common.errors import InputError

__all__ = ["CRFFit", "fit_crf", "used_samples", "simulate_sweep", "average_fit_bias",
           "plot_crf", "load_sweep_csv", "load_sweep_images", "exposure_from_name"]

log = logging.getLogger(__name__)


@dataclass
class CRFFit:
    """Result of :func:`fit_crf`.

    Attributes:
        eps: the shared vertical offset ``ε`` (value units, 0..1).
        gain: ``[P]`` per-pixel slope ``a_j`` (value per unit exposure).
        eps_per_pixel: ``[P]`` intercept of a separate line per pixel (diagnostic; NaN
            for pixels with fewer than 2 used samples).
        residual: RMS of ``a_j e_k − ε − v_kj`` over the used samples.
        used: ``[K, P]`` bool, the samples in the linear range.
    """

    eps: float
    gain: np.ndarray
    eps_per_pixel: np.ndarray
    residual: float
    used: np.ndarray

    def predict(self, exposures: np.ndarray) -> np.ndarray:
        """``[K, P]`` fitted ``clip(a_j e_k − ε, 0, 1)``."""
        return apply_crf(np.asarray(exposures, np.float64)[:, None] * self.gain[None], self.eps)


def used_samples(values: np.ndarray, sat_level: float = 0.95, floor: float = 0.02) -> np.ndarray:
    """``[K, P]`` mask of the linear range: ``floor < v < sat_level``.

    Values at or below ``floor`` are clipped zeros (or zero-clipped noise, whose mean is
    biased upwards); values at or above ``sat_level`` are in the saturation roll-off.
    """
    return (values > floor) & (values < sat_level)


def fit_crf(exposures: np.ndarray, values: np.ndarray, sat_level: float = 0.95,
            floor: float = 0.02, min_points: int = 2) -> CRFFit:
    """Fit ``v = a_j·e − ε`` per pixel with one shared ``ε`` (closed form, module docstring).

    Args:
        exposures: ``[K]`` exposure times (any unit; only ratios matter for ``ε``).
        values: ``[K, P]`` single-pixel values in [0, 1] at each exposure.
        sat_level: values at or above are excluded (saturation roll-off).
        floor: values at or below are excluded (clipped at 0).
        min_points: pixels with fewer used samples are ignored.

    Returns:
        :class:`CRFFit`.

    >>> e = np.linspace(0.1, 1.0, 10)
    >>> v = np.clip(np.outer(e, [0.8, 1.2, 0.5]) - 0.03, 0, 1)
    >>> round(fit_crf(e, v).eps, 6)
    0.03
    """
    e = np.asarray(exposures, np.float64).reshape(-1)
    v = np.asarray(values, np.float64)
    if v.ndim == 1:
        v = v[:, None]
    if v.ndim != 2 or v.shape[0] != e.shape[0]:
        raise InputError("values", "shape", f"[K={e.shape[0]}, P] (one row per exposure)",
                         v.shape)
    used = used_samples(v, sat_level, floor)
    ok = used.sum(0) >= min_points
    if not ok.any():
        raise InputError("values", "linear range",
                         f"some pixel with ≥ {min_points} samples in ({floor}, {sat_level})",
                         "none")
    u = (used & ok[None]).astype(np.float64)
    n = u.sum(0)
    ew = u * e[:, None]
    S, C = (ew * e[:, None]).sum(0), ew.sum(0)
    B, V = (ew * v).sum(0), (u * v).sum(0)
    Sj = np.where(ok, S, 1.0)
    num = np.sum(np.where(ok, V - B * C / Sj, 0.0))
    den = np.sum(np.where(ok, C * C / Sj - n, 0.0))
    if abs(den) < 1e-300:
        raise InputError("exposures", "spread", "at least two distinct exposures per pixel",
                         "one")
    eps = float(num / den)
    gain = np.where(ok, (B + eps * C) / Sj, np.nan)
    res = (gain[None] * e[:, None] - eps - v)[u > 0]
    # separate line per pixel: intercept = −(V − a C)/n with a = (nB − CV)/(nS − C²)
    det = n * S - C * C
    a_sep = np.where(det > 0, (n * B - C * V) / np.where(det > 0, det, 1.0), np.nan)
    eps_sep = np.where(det > 0, -(V - a_sep * C) / np.maximum(n, 1), np.nan)
    fit = CRFFit(eps, gain, eps_sep, float(np.sqrt(np.mean(res ** 2))), used & ok[None])
    log.info("CRF fit: eps = %.5f (%.2f of 255) from %d pixels, %d samples, rms %.4f",
             eps, 255 * eps, int(ok.sum()), int(u.sum()), fit.residual)
    return fit


def simulate_sweep(exposures: np.ndarray, n_pixels: int, eps: float = 3e-2,
                   noise: float = 4e-3, vignetting: float = 0.5, knee: float = 0.95,
                   light: float = 1.0, rng: np.random.Generator | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Values of ``n_pixels`` pixels over an exposure sweep, with the rig's imperfections.

    Pixel ``j`` at normalised radius ``r_j ~ U(0, 1)`` gets irradiance
    ``E = light · (1 − vignetting · r_j²) · e``; its value is
    ``apply_crf(E, eps)`` passed through a smooth saturation roll-off above ``knee``
    (``knee + (1 − knee)·tanh((v − knee)/(1 − knee))``), plus Gaussian noise ``noise``,
    clipped to [0, 1].

    Returns:
        ``(values [K, P], slopes [P])`` with the true slopes ``light·(1 − vignetting·r²)``.
    """
    rng = rng if rng is not None else np.random.default_rng(0)
    e = np.asarray(exposures, np.float64)
    r = rng.uniform(0, 1, n_pixels)
    slopes = light * (1 - vignetting * r ** 2)
    v = apply_crf(e[:, None] * slopes[None], eps)
    span = 1.0 - knee
    v = np.where(v > knee, knee + span * np.tanh((v - knee) / span), v)
    v = np.clip(v + noise * rng.standard_normal(v.shape), 0.0, 1.0)
    return v, slopes


def average_fit_bias(exposures: np.ndarray, values: np.ndarray, sat_level: float = 0.95,
                     floor: float = 0.02) -> tuple[float, float]:
    """``(ε from single pixels, ε from the image average)`` on the same sweep."""
    single = fit_crf(exposures, values, sat_level, floor).eps
    avg = fit_crf(exposures, values.mean(1, keepdims=True), sat_level, floor).eps
    return single, avg


def plot_crf(exposures: np.ndarray, values: np.ndarray, fit: CRFFit, path: str | Path,
             n_show: int = 6) -> Path:
    """Save a plot like the supplementary's Fig. 9: value vs exposure, fits, average.

    Shows ``n_show`` pixels spread over the range of slopes (dots: used samples; crosses:
    excluded), their fitted lines, and the image average (dashed) for comparison.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    e = np.asarray(exposures, np.float64)
    order = np.argsort(np.nan_to_num(fit.gain, nan=-np.inf))
    valid = order[np.isfinite(fit.gain[order])]
    pick = valid[np.linspace(0, len(valid) - 1, min(n_show, len(valid))).astype(int)]
    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    ee = np.linspace(0, e.max(), 200)
    for c, j in enumerate(pick):
        col = f"C{c % 10}"
        ax.plot(e[fit.used[:, j]], 255 * values[fit.used[:, j], j], ".", color=col, ms=4)
        ax.plot(e[~fit.used[:, j]], 255 * values[~fit.used[:, j], j], "x", color=col, ms=3)
        ax.plot(ee, 255 * (fit.gain[j] * ee - fit.eps), "-", color=col, lw=0.8)
    ax.plot(e, 255 * values.mean(1), "k--", lw=1.2, label="image average")
    ax.axhline(0, color="grey", lw=0.5)
    ax.set_ylim(-3 * 255 * fit.eps, 265)
    ax.set_xlabel("exposure")
    ax.set_ylabel("pixel value (0–255)")
    ax.set_title(f"linear CRF, ε = {fit.eps:.4f} ({255 * fit.eps:.2f}/255)")
    ax.legend(loc="lower right")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return path


_NUMBER = re.compile(r"\d+(?:\.\d+)?")


def exposure_from_name(path: Path) -> float:
    """The exposure time in an image file name: the last number of its stem.

    >>> exposure_from_name(Path("cam0_exp_2.5ms.png"))
    2.5
    """
    nums = _NUMBER.findall(Path(path).stem)
    if not nums:
        raise InputError(path, "exposure", "a number in the file name (e.g. exp_2.5ms.png)",
                         Path(path).name)
    return float(nums[-1])


def load_sweep_csv(path: str | Path, max_value: float | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``(exposures [K], values [K, P])`` from a CSV with rows ``exposure, v_1, …, v_P``.

    A header row is skipped if it is not numeric. Values are divided by ``max_value``
    (default: 255 if any value exceeds 1, else 1).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8").splitlines()
    except (FileNotFoundError, UnicodeDecodeError) as e:
        raise InputError(path, "<file>", "a readable CSV file", type(e).__name__) from None
    rows = []
    for i, line in enumerate(text):
        if not line.strip():
            continue
        try:
            rows.append([float(c) for c in line.split(",")])
        except ValueError:
            if rows or i > 0:
                raise InputError(path, f"line {i + 1}", "comma-separated numbers",
                                 line[:40]) from None
    if not rows or len({len(r) for r in rows}) != 1 or len(rows[0]) < 2:
        raise InputError(path, "rows", "equal-length rows: exposure, v_1, …, v_P",
                         sorted({len(r) for r in rows}))
    a = np.asarray(rows, np.float64)
    vals = a[:, 1:]
    scale = max_value if max_value is not None else (255.0 if vals.max() > 1.0 else 1.0)
    return a[:, 0], vals / scale


def load_sweep_images(folder: str | Path, n_pixels: int = 256, border: float = 0.05
                      ) -> tuple[np.ndarray, np.ndarray]:
    """``(exposures [K], values [K, P])`` from 8-bit images named by exposure time.

    Samples single pixels (never averages) on a regular grid of about ``n_pixels``
    positions, ``border`` (fraction) away from the edges; each colour channel of a
    position is its own series (``P = positions × channels``).
    """
    from eventrecon.data.files import read_png

    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "<folder>", "a folder of sweep images", "missing")
    files = sorted(f for f in folder.iterdir() if f.suffix.lower() == ".png")
    if len(files) < 2:
        raise InputError(folder, "images", "at least 2 PNGs named by exposure", len(files))
    exps = np.array([exposure_from_name(f) for f in files])
    imgs = [read_png(f, "image") for f in files]
    for f, im in zip(files, imgs):
        if im.shape != imgs[0].shape:
            raise InputError(f, "image size", f"{imgs[0].shape} as {files[0].name}", im.shape)
    h, w = imgs[0].shape[:2]
    side = max(1, int(round(np.sqrt(n_pixels * w / h))))
    rows = np.linspace(border * h, (1 - border) * (h - 1), max(1, n_pixels // side)).astype(int)
    cols = np.linspace(border * w, (1 - border) * (w - 1), side).astype(int)
    stack = np.stack(imgs).astype(np.float64) / 255.0
    vals = stack[:, rows[:, None], cols[None, :]].reshape(len(files), -1)
    order = np.argsort(exps, kind="stable")
    return exps[order], vals[order]
