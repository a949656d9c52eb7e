"""The four losses of the method, their weights and the sparsity ramp (docs/method.md "Losses").

Notation (per ray ``n`` and channel ``c``): ``Ĉ(t)`` the rendered *linear* colour,
``L(I) = log(I + ε)`` the log space of the events (ε = ``tonemap_eps``, the only guard
against ``log 0``), ``θ`` the contrast threshold, ``M`` the per-ray channel mask,
``E = E(t0, t1)`` and ``E_ref = V(t1) − V(t_ref)`` the accumulated events:

.. math::
   \\mathcal L_{event} &= \\mathrm{mean}_{n,c}\\big(M\\odot[L(Ĉ(t_1)) - L(Ĉ(t_0))]
                         - M\\odot θE\\big)^2 \\\\
   \\mathcal L_{acc}   &= \\mathrm{mean}_{n,c}\\big(M\\odot L(Ĉ(t_1))
                         - M\\odot[L(C_{ref}) + θE_{ref}]\\big)^2 \\\\
   \\mathcal L_{rgb}   &= \\mathrm{mean}_{n,c}\\big(Ĉ(t_{ref}) - C_{ref}\\big)^2 \\\\
   \\mathcal L_{sparsity} &= \\textstyle\\sum_{t \\in \\{t_0, t_1, t_{ref}\\}}
                         \\mathrm{mean}_n\\,(1 - T_{last}(t))

The means run over rays × channels *including* the masked zeros (as the authors' code).
With per-ray loss weights ``w_n`` (a static ``mask/<view>.png`` of the training split,
:class:`~eventrecon.data.types.SplitData` ``loss_mask``) the three photometric terms are
the authors' masked mean instead, ``Σ_{n,c} w_n x_{nc}² / (C·Σ_n w_n + 10⁻⁶)`` with ``C``
the channels compared; the sparsity term is never weighted.

Channel masks (``mask`` argument of the event terms):

- colour (RGGB) event pixels: the Bayer one-hot ``[N, 3]``
  (:func:`eventrecon.events.bayer.bayer_mask_at`) — each pixel constrains the channel
  it sees;
- any other ``[N, 3]`` mask (e.g. all ones) is applied as given;
- ``None`` — grey (non-Bayer) event pixels. DESIGN CHOICE: a grey sensor reports changes
  of one log intensity, so the render is reduced to its channel mean first,
  ``L(mean_c Ĉ)``, and the mean runs over ``N × 1``. (Comparing every channel's log
  change with the grey event would force colour changes to be grey.)

Total (per level, summed over the coarse and fine levels):

.. math:: \\mathcal L = w_{ev}\\mathcal L_{event} + w_{acc}\\mathcal L_{acc}
          + w_{rgb}\\mathcal L_{rgb} + λ(1 - e^{-step/ramp})\\,\\mathcal L_{sparsity}
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from eventrecon.common.errors import InputError, as_number

__all__ = [
    "LossConfig",
    "log_intensity",
    "event_channels",
    "event_loss",
    "acc_loss",
    "rgb_loss",
    "sparsity_loss",
    "sparsity_weight",
    "total_loss",
]


@dataclass
class LossConfig:
    """Weights and constants of the losses (defaults: docs/method.md, synthetic data)."""

    w_event: float = 1.0
    """Weight of L_event (0 disables it: the "w/o L_event" ablation)."""
    w_acc: float = 1.0
    """Weight of L_acc (0 disables it)."""
    w_rgb: float = 0.01
    """Weight of L_rgb (0 disables it)."""
    lam_sparsity: float = 1e-2
    """λ of the sparsity term (0 disables it: "w/o L_sparsity")."""
    sparsity_ramp: float = 30000.0
    """Steps of the ramp ``1 − exp(−step/ramp)``; 0 means no ramp (full λ at once)."""
    eps: float = 1e-2
    """``tonemap_eps`` ε of the log space: 1e-2 synthetic, 3e-2 real data."""
    theta: float = 0.5
    """Event contrast threshold θ in that log space."""

    def __post_init__(self) -> None:
        for name in ("w_event", "w_acc", "w_rgb", "lam_sparsity", "sparsity_ramp"):
            x = as_number(getattr(self, name))
            if not (math.isfinite(x) and x >= 0):
                raise InputError("config", f"loss.{name}", "a finite number >= 0",
                                 getattr(self, name))
        if not as_number(self.eps) > 0:       # eps and theta come from the data's settings
            raise InputError("loss config", "eps", "a number > 0 (the guard of log)", self.eps)
        if not as_number(self.theta) > 0:
            raise InputError("loss config", "theta", "a number > 0", self.theta)


def log_intensity(rgb: Tensor, eps: float) -> Tensor:
    """``L(I) = log(I + ε)``, elementwise; finite with finite gradient ``1/(I+ε)`` at I = 0.

    >>> log_intensity(torch.tensor([0.0, 1.0]), 1.0)
    tensor([0.0000, 0.6931])
    """
    return torch.log(rgb + eps)


def event_channels(rgb: Tensor, mask: Tensor | None) -> tuple[Tensor, Tensor]:
    """The linear intensities the event terms compare, and their mask.

    Args:
        rgb: ``[N, 3]`` linear colour (render or reference); a single-channel reference
            ``[N]`` (Bayer raw or grey) is broadcast to every channel.
        mask: ``[N, 3]`` channel mask, or ``None`` for grey event pixels.

    Returns:
        ``(I [N, C], M [N, C])`` with ``C = 3`` (``I = rgb``, ``M = mask``) or, for
        ``mask=None``, ``C = 1`` (``I = mean_c rgb``, ``M = 1``).
    """
    if mask is None:
        grey = rgb[:, None] if rgb.dim() == 1 else rgb.mean(-1, keepdim=True)
        return grey, torch.ones_like(grey)
    if rgb.dim() == 1:
        rgb = rgb[:, None].expand(-1, 3)
    if mask.shape != rgb.shape:
        raise InputError("losses", "mask", f"shape {tuple(rgb.shape)}", tuple(mask.shape))
    return rgb, mask.to(rgb.dtype)


def _mean(sq: Tensor, weight: Tensor | None) -> Tensor:
    """``mean(sq)`` of ``sq [N, C]`` (or ``[N]``), or with per-ray ``weight [N]`` the
    authors' masked mean ``Σ w_n sq_nc / (C·Σ w_n + 10⁻⁶)``."""
    if weight is None:
        return sq.mean()
    w, sq = weight.to(sq.dtype), sq.reshape(weight.shape[0], -1)
    return (sq * w[:, None]).sum() / (sq.shape[1] * w.sum() + 1e-6)


def _masked_mse(pred: Tensor, target: Tensor, mask: Tensor, weight: Tensor | None) -> Tensor:
    """``mean((M⊙pred − M⊙target)²)`` over every element, masked zeros included
    (:func:`_mean` with per-ray ``weight``)."""
    return _mean((mask * (pred - target)) ** 2, weight)


def event_loss(rgb_t0: Tensor, rgb_t1: Tensor, events: Tensor, mask: Tensor | None,
               eps: float, theta: float, weight: Tensor | None = None) -> Tensor:
    """L_event: the rendered log change over the window against ``θ·E(t0, t1)``.

    Args:
        rgb_t0, rgb_t1: ``[N, 3]`` linear renders at ``t0`` and ``t1``.
        events: ``[N]`` accumulated events ``E(t0, t1)`` of each ray's pixel.
        mask: ``[N, 3]`` channel mask (Bayer one-hot) or ``None`` (grey events).
        eps, theta: log-space ε and threshold θ.
        weight: ``[N]`` per-ray loss weights or ``None`` (module docstring).

    Returns:
        scalar ``mean_{n,c}(M⊙[L(Ĉ1) − L(Ĉ0)] − M⊙θE)²``.

    >>> x0 = torch.full((1, 3), 0.5); x1 = x0 * math.e  # log change of exactly 1
    >>> event_loss(x0, x1, torch.tensor([1.0]), torch.tensor([[1.0, 0, 0]]), 0.0, 0.5)
    tensor(0.0833)
    """
    i0, m = event_channels(rgb_t0, mask)
    i1, _ = event_channels(rgb_t1, mask)
    diff = log_intensity(i1, eps) - log_intensity(i0, eps)
    return _masked_mse(diff, theta * events.to(diff.dtype)[:, None], m, weight)


def acc_loss(rgb_t1: Tensor, ref_rgb: Tensor, events_ref: Tensor, mask: Tensor | None,
             eps: float, theta: float, weight: Tensor | None = None) -> Tensor:
    """L_acc: the render at ``t1`` against the reference frame advanced by its events.

    Args:
        rgb_t1: ``[N, 3]`` linear render at ``t1``.
        ref_rgb: ``[N, 3]`` linear reference colour, or ``[N]`` single-channel raw value.
        events_ref: ``[N]`` ``E_ref→1 = V(t1) − V(t_ref)`` (either time order).
        mask, eps, theta, weight: as in :func:`event_loss`.

    Returns:
        scalar ``mean_{n,c}(M⊙L(Ĉ(t1)) − M⊙[L(C_ref) + θE_ref])²``.
    """
    i1, m = event_channels(rgb_t1, mask)
    iref, _ = event_channels(ref_rgb.to(i1.dtype), mask)
    target = log_intensity(iref, eps) + theta * events_ref.to(i1.dtype)[:, None]
    return _masked_mse(log_intensity(i1, eps), target, m, weight)


def rgb_loss(rgb_ref: Tensor, ref_rgb: Tensor, raw_mask: Tensor | None = None,
             weight: Tensor | None = None) -> Tensor:
    """L_rgb: linear-space MSE of the render at ``t_ref`` against the reference frame.

    Args:
        rgb_ref: ``[N, 3]`` linear render at ``t_ref``.
        ref_rgb: ``[N, 3]`` linear reference, or ``[N]`` single-channel Bayer raw.
        raw_mask: ``[N, 3]`` Bayer one-hot of the raw pixels (required for ``[N]``
            references): the render is masked and summed to the channel the pixel saw.
        weight: ``[N]`` per-ray loss weights or ``None`` (module docstring).

    Returns:
        scalar ``mean_{n,c}(Ĉ − C_ref)²`` or, raw, ``mean_n(Σ_c M⊙Ĉ − C_raw)²``.

    >>> rgb_loss(torch.tensor([[0.2, 0.4, 0.6]]), torch.tensor([0.4]),
    ...          torch.tensor([[0.0, 1.0, 0.0]]))
    tensor(0.)
    """
    if ref_rgb.dim() == 1:
        if raw_mask is None:
            raise InputError("losses", "raw_mask", "a [N, 3] Bayer mask for a raw reference")
        pred = (rgb_ref * raw_mask.to(rgb_ref.dtype)).sum(-1)
        return _mean((pred - ref_rgb.to(pred.dtype)) ** 2, weight)
    return _mean((rgb_ref - ref_rgb.to(rgb_ref.dtype)) ** 2, weight)


def sparsity_loss(opacities: Sequence[Tensor]) -> Tensor:
    """L_sparsity: ``Σ_renders mean_n(1 − T_last)`` (opacity = accumulated weight).

    Args:
        opacities: the ``[N]`` opacities ``1 − T_last`` of the renders at t0, t1, t_ref.

    >>> sparsity_loss([torch.tensor([0.0, 1.0]), torch.tensor([0.5, 0.5])])
    tensor(1.)
    """
    return torch.stack([o.mean() for o in opacities]).sum()


def sparsity_weight(step: int, lam: float = 1e-2, ramp: float = 30000.0) -> float:
    """``λ·(1 − exp(−step/ramp))``; ``ramp = 0`` gives ``λ`` from step 0.

    >>> round(sparsity_weight(30000), 6)
    0.006321
    """
    if ramp <= 0:
        return float(lam)
    return float(lam) * (1.0 - math.exp(-float(step) / float(ramp)))


def total_loss(levels: Sequence[dict[str, Tensor]], batch: dict[str, Tensor | None],
               cfg: LossConfig, step: int) -> dict[str, Tensor]:
    """All enabled terms summed over the render levels, and the weighted total.

    Args:
        levels: one dict per level (coarse, fine) with ``rgb_t0, rgb_t1, rgb_ref [N,3]``
            and ``opacity_t0, opacity_t1, opacity_ref [N]``.
        batch: ``events [N]`` (E(t0,t1)), ``events_ref [N]`` (V(t1) − V(t_ref)),
            ``ref_rgb [N,3]`` or ``[N]`` raw, ``mask [N,3]`` or ``None`` (event-pixel
            channel mask, see the module docstring) and optionally ``raw_mask [N,3]``
            (Bayer mask of raw reference frames; defaults to ``mask``) and ``weight [N]``
            (per-ray loss weights, module docstring; ``None`` or absent: plain means).
        cfg: weights and constants.
        step: the global step (for the sparsity ramp).

    Returns:
        ``{"event", "acc", "rgb", "sparsity"}`` — each the unweighted sum over levels,
        present only when its weight is non-zero (a disabled term is not computed) —
        plus ``"sparsity_weight"`` (when sparsity is on) and ``"loss"``, the weighted sum.
    """
    if not levels:
        raise InputError("total_loss", "levels", "at least one render level", 0)
    mask, weight = batch.get("mask"), batch.get("weight")
    out: dict[str, Tensor] = {}
    terms: list[tuple[str, float]] = []
    if cfg.w_event > 0:
        out["event"] = sum(event_loss(lv["rgb_t0"], lv["rgb_t1"], batch["events"], mask,
                                      cfg.eps, cfg.theta, weight) for lv in levels)
        terms.append(("event", cfg.w_event))
    if cfg.w_acc > 0:
        out["acc"] = sum(acc_loss(lv["rgb_t1"], batch["ref_rgb"], batch["events_ref"], mask,
                                  cfg.eps, cfg.theta, weight) for lv in levels)
        terms.append(("acc", cfg.w_acc))
    if cfg.w_rgb > 0:
        raw_mask = batch.get("raw_mask", mask)
        out["rgb"] = sum(rgb_loss(lv["rgb_ref"], batch["ref_rgb"], raw_mask, weight)
                         for lv in levels)
        terms.append(("rgb", cfg.w_rgb))
    if cfg.lam_sparsity > 0:
        out["sparsity"] = sum(
            sparsity_loss([lv["opacity_t0"], lv["opacity_t1"], lv["opacity_ref"]])
            for lv in levels)
        w = sparsity_weight(step, cfg.lam_sparsity, cfg.sparsity_ramp)
        out["sparsity_weight"] = torch.tensor(w)
        terms.append(("sparsity", w))
    if not terms:
        raise InputError("loss config", "weights", "at least one non-zero loss weight",
                         "all zero")
    out["loss"] = sum(w * out[name] for name, w in terms)
    return out
