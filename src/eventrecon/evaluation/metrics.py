"""Image quality metrics: PSNR, SSIM, LPIPS-Alex and LPIPS-VGG, and an optional colour correction.

Images are ``[H, W, 3]`` (or batched ``[N, H, W, 3]``) float arrays in ``[0, 1]``,
numpy or torch (any device). Conventions of the paper's evaluation:

- PSNR ``= -10 log10(mean((pred - gt)²))`` (peak 1); ``inf`` for identical images.
- SSIM: :func:`skimage.metrics.structural_similarity` with ``data_range=1`` and
  ``channel_axis=-1`` (Gaussian-free 7×7 window, scikit-image defaults).
- LPIPS: :class:`eventrecon.evaluation.lpips.LPIPS` on inputs mapped to ``[-1, 1]``
  (``2x - 1``), with the AlexNet trunk (key ``lpips``, the paper's) and the VGG16 trunk
  (key ``lpips_vgg``). When a network's weights cannot be had, its LPIPS is
  *unavailable*: :func:`evaluate_images` returns ``None`` and a one-line note
  (``lpips_note``, ``lpips_vgg_note``), never 0.
- Colour correction (:data:`CORRECTIONS`, ``none`` by default): ``per_image`` fits, per
  image and channel, ``log(gt + eps) ≈ a·log(pred + eps) + b`` by least squares on the
  encoded values and replaces ``pred`` by ``exp(a·log(pred + eps) + b) - eps`` clipped to
  ``[0, 1]`` (:func:`color_correct`); ``eventnerf`` is EventNeRF's evaluation: one such
  fit per channel over every pixel of every image jointly, in linear radiance with an
  offset of 0.1 (:func:`color_correct_joint`).

>>> import numpy as np
>>> gt = np.full((8, 8, 3), 0.5); pred = gt + 0.1
>>> round(psnr(pred, gt), 6)
20.0
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np
import torch
from skimage.metrics import structural_similarity

from eventrecon.common.colour import GAMMA
from eventrecon.common.errors import InputError
from eventrecon.evaluation.lpips import NETS, LPIPSUnavailable, load_lpips

log = logging.getLogger(__name__)

ArrayLike = np.ndarray | torch.Tensor
_WARNED: set[str] = set()


def _as_numpy(img: ArrayLike) -> np.ndarray:
    if isinstance(img, torch.Tensor):
        return img.detach().to("cpu", torch.float64).numpy()
    return np.asarray(img, dtype=np.float64)


def _batch(img: ArrayLike, name: str) -> np.ndarray:
    """``[H,W,3]`` or ``[N,H,W,3]`` → float64 ``[N,H,W,3]``; otherwise :class:`InputError`."""
    arr = _as_numpy(img)
    if arr.ndim == 3:
        arr = arr[None]
    if arr.ndim != 4 or arr.shape[-1] != 3:
        raise InputError(f"metrics({name})", "shape", "[H, W, 3] or [N, H, W, 3]", arr.shape)
    return arr


def _pair(pred: ArrayLike, gt: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    p, g = _batch(pred, "pred"), _batch(gt, "gt")
    if p.shape != g.shape:
        raise InputError("metrics(pred)", "shape", f"equal to gt's {g.shape}", p.shape)
    return p, g


def psnr(pred: ArrayLike, gt: ArrayLike) -> float:
    """PSNR in dB of one ``[H,W,3]`` image (peak 1): ``-10·log10(MSE)``; ``inf`` if equal.

    A batch ``[N,H,W,3]`` gives the mean of the per-image PSNRs.

    >>> import numpy as np
    >>> round(psnr(np.zeros((4, 4, 3)), np.full((4, 4, 3), 0.01)), 6)
    40.0
    """
    p, g = _pair(pred, gt)
    mse = ((p - g) ** 2).reshape(len(p), -1).mean(axis=1)
    with np.errstate(divide="ignore"):
        vals = -10.0 * np.log10(mse)
    return float(np.mean(vals))


def ssim(pred: ArrayLike, gt: ArrayLike) -> float:
    """SSIM (scikit-image, ``data_range=1``, ``channel_axis=-1``); mean over a batch.

    >>> import numpy as np
    >>> ssim(np.full((16, 16, 3), 0.3), np.full((16, 16, 3), 0.3))
    1.0
    """
    p, g = _pair(pred, gt)
    vals = [
        structural_similarity(a, b, data_range=1.0, channel_axis=-1) for a, b in zip(p, g)
    ]
    return float(np.mean(vals))


def subject_scores(pred: ArrayLike, gt: ArrayLike, mask: np.ndarray) -> dict[str, float]:
    """PSNR and SSIM on the subject's region: per image, the MSE over the ``mask`` pixels
    (``-10·log10`` of it) and the mean of the SSIM map over them; means over the images
    whose mask is not empty (``{}`` when none is).

    Args:
        pred, gt: ``[N, H, W, 3]`` (or one ``[H, W, 3]``) images in [0, 1].
        mask: ``[N, H, W]`` (or ``[H, W]``) bool, the subject's pixels.

    >>> import numpy as np
    >>> gt = np.zeros((1, 8, 8, 3)); pred = gt.copy(); pred[0, :4] = 0.1
    >>> m = np.zeros((1, 8, 8), bool); m[0, :4] = True
    >>> round(subject_scores(pred, gt, m)["psnr_subject"], 6), round(psnr(pred, gt), 6)
    (20.0, 23.0103)
    """
    p, g = _pair(pred, gt)
    m = np.asarray(mask, bool).reshape(p.shape[:3])
    ps, ss = [], []
    for a, b, k in zip(p, g, m):
        if not k.any():
            continue
        mse = float(((a - b) ** 2)[k].mean())
        ps.append(math.inf if mse == 0 else -10.0 * math.log10(mse))
        _, smap = structural_similarity(a, b, data_range=1.0, channel_axis=-1, full=True)
        ss.append(float(smap[k].mean()))
    return {"psnr_subject": float(np.mean(ps)), "ssim_subject": float(np.mean(ss))} if ps else {}


#: The result key of each LPIPS network in :func:`evaluate_images` (its note: ``<key>_note``).
LPIPS_KEYS: dict[str, str] = {"alex": "lpips", "vgg": "lpips_vgg"}


def lpips(
    pred: ArrayLike, gt: ArrayLike, device: torch.device | str | None = None, net: str = "alex"
) -> float:
    """LPIPS v0.1 distance with the ``net`` trunk (lower is better); mean over a batch.

    Inputs in ``[0, 1]`` are mapped to ``[-1, 1]`` before the network. Raises
    :class:`eventrecon.evaluation.lpips.LPIPSUnavailable` when the weights cannot be had.
    ``device`` defaults to the device of ``pred`` when it is a tensor, else CPU.
    """
    if device is None:
        device = pred.device if isinstance(pred, torch.Tensor) else "cpu"
    p, g = _pair(pred, gt)
    if min(p.shape[1:3]) < NETS[net].min_size:
        raise LPIPSUnavailable(f"{NETS[net].label}: {p.shape[1]}×{p.shape[2]} images are "
                               f"smaller than its {NETS[net].min_size} px")
    model = load_lpips(net, device)
    vals = []
    with torch.no_grad():
        for a, b in zip(p, g):
            ta = torch.as_tensor(a, dtype=torch.float32, device=device).permute(2, 0, 1)[None]
            tb = torch.as_tensor(b, dtype=torch.float32, device=device).permute(2, 0, 1)[None]
            vals.append(float(model(2 * ta - 1, 2 * tb - 1)[0]))
    return float(np.mean(vals))


def color_correct(pred: ArrayLike, gt: ArrayLike, eps: float = 1e-2) -> np.ndarray:
    """Per-image, per-channel affine fit in log space of ``pred`` to ``gt``.

    For each image and channel ``c``: ``(a, b) = argmin Σ (a·log(pred+eps) + b
    - log(gt+eps))²`` (ordinary least squares over the pixels), then
    ``pred' = clip(exp(a·log(pred+eps) + b) - eps, 0, 1)``. A constant channel
    (no variance) gets ``a = 0`` and ``b`` = the mean of ``log(gt+eps)``.

    Returns float64 ``[N,H,W,3]`` (or ``[H,W,3]`` for a single image input).

    >>> import numpy as np
    >>> gt = np.linspace(0.1, 0.9, 48).reshape(4, 4, 3)
    >>> pred = np.exp(0.5 * np.log(gt + 1e-2)) - 1e-2  # log-affine distortion of gt
    >>> bool(np.abs(color_correct(pred, gt) - gt).max() < 1e-9)
    True
    """
    single = _as_numpy(pred).ndim == 3
    p, g = _pair(pred, gt)
    lp, lg = np.log(np.clip(p, 0, None) + eps), np.log(np.clip(g, 0, None) + eps)
    out = np.empty_like(p)
    for n in range(len(p)):
        for c in range(3):
            x, y = lp[n, ..., c].ravel(), lg[n, ..., c].ravel()
            xc = x - x.mean()
            var = float(xc @ xc)
            a = float(xc @ (y - y.mean())) / var if var > 0 else 0.0
            b = y.mean() - a * x.mean()
            out[n, ..., c] = np.exp(a * lp[n, ..., c] + b) - eps
    out = np.clip(out, 0.0, 1.0)
    return out[0] if single else out


def color_correct_joint(pred: ArrayLike, gt: ArrayLike, offset: float = 0.1) -> np.ndarray:
    """EventNeRF's colour correction: one per-channel affine fit in log-linear space over
    all pixels of all images jointly.

    With ``lin(x) = x^2.2`` (the dataset's gamma), ``u = log(lin(pred) + offset)`` and
    ``v = log(lin(gt) + offset)``, for each channel ``c``: ``(a_c, b_c) = argmin
    Σ_{n,h,w} (a_c u + b_c − v)²``; then ``pred' = clip(exp(a_c u + b_c) − offset, 0,
    1)^(1/2.2)``. One fit for the run's whole held-out set corrects its global tone and
    white balance, not each image's.

    Returns float64 ``[N,H,W,3]`` (or ``[H,W,3]`` for a single image input).

    >>> import numpy as np
    >>> gt = np.linspace(0.1, 0.9, 96).reshape(2, 4, 4, 3)
    >>> lin = np.exp(0.8 * np.log(gt ** GAMMA + 0.1) + 0.05) - 0.1   # one tone curve
    >>> bool(np.abs(color_correct_joint(lin ** (1 / GAMMA), gt) - gt).max() < 1e-9)
    True
    """
    single = _as_numpy(pred).ndim == 3
    p, g = _pair(pred, gt)
    u = np.log(np.clip(p, 0, 1) ** GAMMA + offset)
    v = np.log(np.clip(g, 0, 1) ** GAMMA + offset)
    out = np.empty_like(p)
    for c in range(3):
        x, y = u[..., c].ravel(), v[..., c].ravel()
        a, b = np.polyfit(x, y, 1) if np.ptp(x) > 0 else (0.0, float(y.mean()))
        out[..., c] = np.clip(np.exp(a * u[..., c] + b) - offset, 0.0, 1.0) ** (1.0 / GAMMA)
    return out[0] if single else out


#: Colour corrections before the metrics (module docstring); ``none`` is the default.
CORRECTIONS: tuple[str, ...] = ("none", "per_image", "eventnerf")


def correction_mode(value: bool | str) -> str:
    """A colour-correction setting as one of :data:`CORRECTIONS` (``True`` is
    ``per_image``, ``False`` ``none``)."""
    if isinstance(value, bool):
        return "per_image" if value else "none"
    if value not in CORRECTIONS:
        raise InputError("evaluation", "color_correct", f"one of {', '.join(CORRECTIONS)}", value)
    return value


def evaluate_images(
    preds: ArrayLike,
    gts: ArrayLike,
    lpips: bool | tuple[str, ...] = True,
    color_correct: bool | str = "none",
    device: torch.device | str | None = None,
) -> dict[str, Any]:
    """Mean PSNR / SSIM / LPIPS over frames ``[N,H,W,3]`` (or one ``[H,W,3]`` image).

    Returns ``{"psnr", "ssim", "lpips", "lpips_note", "lpips_vgg", "lpips_vgg_note",
    "n_frames", "color_corrected"}``. ``lpips``: ``True`` for both networks, ``False``
    for none, or the names of those to compute (``("alex",)``). A network's value is
    ``None`` (with a one-line note and a logged warning) when its weights cannot be had
    or it was not asked for; never a made-up 0 (the warning is logged once per reason).
    ``color_correct`` (:data:`CORRECTIONS`) fits the predictions to the ground truth first,
    per image (:func:`color_correct`) or jointly (:func:`color_correct_joint`); the
    metrics then measure structure more than tone. ``color_corrected`` names the mode.

    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> gt = rng.random((2, 16, 16, 3)); out = evaluate_images(gt, gt, lpips=False)
    >>> out["psnr"], out["ssim"], out["lpips"], out["lpips_note"]
    (inf, 1.0, None, 'LPIPS-Alex not requested')
    """
    p, g = _pair(preds, gts)
    if device is None and isinstance(preds, torch.Tensor):
        device = preds.device
    mode = correction_mode(color_correct)
    if mode == "per_image":
        p = _color_correct_fn(p, g)
    elif mode == "eventnerf":
        p = color_correct_joint(p, g)
    result: dict[str, Any] = {
        "psnr": psnr(p, g),
        "ssim": ssim(p, g),
        "n_frames": int(len(p)),
        "color_corrected": mode,
    }
    nets = tuple(NETS) if lpips is True else tuple(lpips or ())
    for net, key in LPIPS_KEYS.items():
        result[key], result[f"{key}_note"] = None, f"{NETS[net].label} not requested"
        if net not in nets:
            continue
        try:
            result[key] = _lpips_fn(p, g, device=device, net=net)
            result[f"{key}_note"] = None
        except LPIPSUnavailable as exc:
            note = str(exc).splitlines()[0] if str(exc) else f"{NETS[net].label} unavailable"
            if note not in _WARNED:  # once per reason, not at every evaluation
                _WARNED.add(note)
                log.warning("LPIPS unavailable: %s", note)
            result[f"{key}_note"] = note
    if math.isinf(result["psnr"]):
        log.debug("PSNR is infinite: predictions equal the ground truth")
    return result


# Keyword arguments of evaluate_images shadow the functions of the same name.
_color_correct_fn = color_correct
_lpips_fn = lpips
