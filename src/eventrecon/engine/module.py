"""The LightningModule: one training step = sample a window, render, compute the losses.

Per step (docs/method.md "Per-iteration sampling"):

1. ``batch = batcher.sample(n_rays, gen)`` with ``gen`` seeded by ``(seed, step, rank)`` —
   the batch is a pure function of the step, so a resumed run replays the same batches,
   and DDP ranks draw different rays;
2. every pixel is rendered at three times ``t0, t1, t_ref`` in one renderer call (the
   samples stacked ``[3N]``; :mod:`eventrecon.render.renderer`), coarse and fine levels
   of the volume renderer by ONE field;
3. :func:`eventrecon.engine.losses.total_loss` sums L_event, L_acc, L_rgb and the ramped
   L_sparsity over both levels; the field's own regulariser (e.g. TV) is added.

A non-finite loss skips the step (``training_step`` returns ``None``, so no backward and
no optimiser step), is logged as ``train/nonfinite_steps``, and ``max_nonfinite`` in a row
stop the run with a checkpoint and a one-line reason.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch import Tensor

from eventrecon.common.errors import InputError
from eventrecon.data.batcher import RayBatcher
from eventrecon.data.datamodule import StepCounter
from eventrecon.engine.losses import LossConfig, total_loss
from eventrecon.fields.base import Field
from eventrecon.render.renderer import Renderer
from eventrecon.results import records

__all__ = ["EventNeRFModule", "StepConfig", "NonFiniteLossError", "step_generator",
           "adamw_fused", "field_class_name"]

log = logging.getLogger(__name__)


class NonFiniteLossError(RuntimeError):
    """Raised after ``max_nonfinite`` consecutive non-finite losses (one-line message)."""


def field_class_name(field: Field) -> str:
    """``module.QualName`` of a field, as recorded in checkpoints (``eventrecon.field_class``).

    >>> from eventrecon.fields.nerf import NeRFField
    >>> field_class_name(NeRFField(depth=2, width=8, skip=-1, pos_bands=2, time_bands=1))
    'eventrecon.fields.nerf.NeRFField'
    """
    return f"{type(field).__module__}.{type(field).__qualname__}"


@dataclass
class StepConfig:
    """Per-step settings of a run (from ``cfg.trainer`` and ``cfg.model.optim``)."""

    n_rays: int = 256
    lr: float = 1e-4
    weight_decay: float = 0.0
    betas: tuple[float, ...] = (0.9, 0.999)
    eps: float = 1e-8
    max_nonfinite: int = 20
    log_every: int = 25
    seed: int = 0
    max_steps: int = 1
    lr_end_factor: float = 1.0
    lr_warmup: int = 0
    lr_decay_start: float = 0.0


def lr_factor(step: int, max_steps: int, end_factor: float, warmup: int = 0,
              decay_start: float = 0.0) -> float:
    r"""The learning-rate multiplier at ``step`` of a segment of ``max_steps = S`` steps.

    A linear warm-up over the first ``W = warmup`` steps times an exponential decay that
    starts at step :math:`s_0 = a S` (``a = decay_start``),

    .. math:: \min(1, s/W)\cdot f^{\,\mathrm{clip}((s - s_0)/(S - s_0),\ 0,\ 1)}:

    the decay is 1 up to step :math:`s_0` and reaches ``end_factor = f`` at step ``S``
    (``a = 0``: over the whole segment). The warm-up is the authors' scheduler's
    ``it/4000`` (``use_lr_scheduler``, which their runs switch off); ``W = 0`` and
    ``f = 1`` keep the lr constant, as their runs do.

    >>> [round(lr_factor(s, 100, 0.1), 4) for s in (0, 50, 100)]
    [1.0, 0.3162, 0.1]
    >>> lr_factor(7, 100, 1.0)
    1.0
    >>> [lr_factor(s, 100, 1.0, warmup=4) for s in (0, 1, 3, 4, 50)]
    [0.0, 0.25, 0.75, 1.0, 1.0]
    >>> [round(lr_factor(s, 100, 0.1, decay_start=0.5), 4) for s in (0, 50, 75, 100)]
    [1.0, 1.0, 0.3162, 0.1]
    """
    warm = min(1.0, step / warmup) if warmup > 0 else 1.0
    if end_factor == 1.0 or max_steps <= 0:
        return float(warm)
    start = decay_start * max_steps
    progress = min(max(step - start, 0.0) / (max_steps - start), 1.0)
    return float(warm * end_factor ** progress)


def adamw_fused(groups: list[dict[str, Any]]) -> bool:
    """Whether AdamW can run fused (one kernel per parameter instead of a dozen passes):
    every parameter a floating-point tensor on a CPU or a CUDA device. The same update up
    to rounding; per step on 2 cores, NeRF 4×64 0.54 → 0.10 ms, NGP 7.8 → 0.7 ms
    (docs/results/history.md, "Session 47")."""
    params = [p for g in groups for p in g["params"]]
    return bool(params) and all(p.is_floating_point() and p.device.type in ("cpu", "cuda")
                                for p in params)


def state_like_params(optimizer: torch.optim.Optimizer) -> None:
    """Lay every per-parameter state tensor out as its parameter (the same strides).

    A fused optimiser walks a parameter, its gradient and its moments as flat memory, so
    a moment loaded with other strides would be paired with the wrong elements. That
    happens when a checkpoint's moments were written in another layout: before the
    factorised backbones stored their factors channel-last on a CPU
    (``baselines.grids.device_layout``), or on another device. Registered as the
    optimiser's load hook by :meth:`EventNeRFModule.configure_optimizers`."""
    for param, state in optimizer.state.items():
        for key, value in state.items():
            if (isinstance(value, Tensor) and value.shape == param.shape
                    and value.stride() != param.stride()):
                state[key] = torch.empty_like(param, dtype=value.dtype).copy_(value)


def step_generator(seed: int, step: int, stream: int = 0) -> torch.Generator:
    """A CPU generator determined by ``(seed, step, stream)`` (SplitMix-style mixing)."""
    x = (seed * 0x9E3779B97F4A7C15 + step * 0xBF58476D1CE4E5B9 + stream * 0x94D049BB133111EB)
    return torch.Generator().manual_seed(x & ((1 << 63) - 1))


class EventNeRFModule(L.LightningModule):
    """Trains one :class:`~eventrecon.fields.base.Field` on one segment.

    Args:
        field: the representation backbone.
        renderer: the :class:`~eventrecon.render.renderer.Renderer` of the field.
        batcher: draws the training batch of the segment; ``None`` takes the one the
            trainer's :class:`~eventrecon.data.datamodule.SegmentDataModule` builds on
            this process's device in ``setup``.
        loss: loss weights, ε and θ.
        step: rays per step, optimiser and guard settings.
    """

    def __init__(self, field: Field, renderer: Renderer, batcher: RayBatcher | None,
                 loss: LossConfig, step: StepConfig) -> None:
        super().__init__()
        self.field = field
        self.renderer = renderer
        self.batcher = batcher
        self.loss_cfg = loss
        self.step_cfg = step
        self.nonfinite_in_row = 0
        self.nonfinite_total = 0
        self.stop_reason: str | None = None
        self.last_window: tuple[float, float] = (0.0, 1.0)  # (t0, t1) of the last step
        #: ``(step, mean opacity)`` of the fine level's three renders, every ``log_every``
        #: steps (the collapse check, :mod:`eventrecon.engine.collapse`)
        self.opacity_log: list[tuple[int, float]] = []
        #: the dataset folder's name the runner trains on (recorded in checkpoints)
        self.data_id: str | None = None

    def setup(self, stage: str) -> None:
        """Take the DataModule's batcher (built on this process's device)."""
        if self.batcher is None:
            dm = getattr(self.trainer, "datamodule", None)
            if dm is None or getattr(dm, "batcher", None) is None:
                raise RuntimeError("EventNeRFModule without a batcher needs a "
                                   "SegmentDataModule passed to trainer.fit(datamodule=...)")
            self.batcher = dm.batcher

    # ------------------------------------------------------------------ optimiser
    def configure_optimizers(self) -> torch.optim.Optimizer:
        """AdamW over the field's parameter groups (re-run by growth schedules), in one
        fused pass per parameter where the devices allow (:func:`adamw_fused`; loaded moments
        take their parameters' layout, :func:`state_like_params`). Each group
        keeps its own lr as ``base_lr``; :meth:`training_step` scales it by
        :func:`lr_factor` (constant unless ``trainer.lr_end_factor < 1`` or
        ``trainer.lr_warmup > 0``; ``trainer.lr_decay_start`` delays the decay)."""
        cfg = self.step_cfg
        groups = self.field.param_groups(cfg.lr)
        for g in groups:
            g["base_lr"] = float(g.get("lr", cfg.lr))
        opt = torch.optim.AdamW(groups, lr=cfg.lr, weight_decay=cfg.weight_decay,
                                betas=cfg.betas, eps=cfg.eps, fused=adamw_fused(groups))
        opt.register_load_state_dict_post_hook(state_like_params)
        return opt

    def _set_lr(self, step: int) -> None:
        """Every group's lr = its ``base_lr`` × :func:`lr_factor` at ``step``."""
        cfg = self.step_cfg
        if cfg.lr_end_factor == 1.0 and cfg.lr_warmup <= 0:
            return
        f = lr_factor(step, cfg.max_steps, cfg.lr_end_factor, cfg.lr_warmup,
                      cfg.lr_decay_start)
        for opt in self.trainer.optimizers:
            for g in opt.param_groups:
                g["lr"] = g.get("base_lr", g["lr"]) * f

    # ------------------------------------------------------------------ training
    def render_three(self, batch: dict[str, Tensor], gen: torch.Generator | None,
                     perturb: bool = True) -> list[dict[str, Tensor]]:
        """Render each pixel at ``t0, t1, t_ref`` in one renderer call (the samples stacked
        ``[3N]``, ``copies=3``); per level a dict of ``[N, ...]`` outputs with keys
        ``rgb_t0, rgb_t1, rgb_ref, opacity_t0, opacity_t1, opacity_ref``."""
        n = batch["view"].shape[0]
        t = torch.cat([batch["t0"], batch["t1"], batch["t_ref"]], 0)
        levels = self.renderer(self.field, self.batcher.cameras, batch["view"].repeat(3),
                               batch["uv"].repeat(3, 1), t, batch["bg"].repeat(3, 1),
                               perturb=perturb, gen=gen, copies=3)
        out = []
        for lv in levels:
            rgb, opa = lv["rgb"].split(n), lv["opacity"].split(n)
            out.append({"rgb_t0": rgb[0], "rgb_t1": rgb[1], "rgb_ref": rgb[2],
                        "opacity_t0": opa[0], "opacity_t1": opa[1], "opacity_ref": opa[2]})
        return out

    def training_step(self, _: Any, batch_idx: int) -> Tensor | None:
        step = int(self.global_step)
        gen = step_generator(self.step_cfg.seed, step, stream=int(self.global_rank))
        batch = self.batcher.sample(self.step_cfg.n_rays, gen)
        self._set_lr(step)
        n_rays = int(batch["view"].shape[0])
        self.last_window = self.batcher.last_window  # Python floats: no device sync
        levels = self.render_three(batch, gen)
        terms = total_loss(levels, batch, self.loss_cfg, step)
        loss = terms["loss"]
        reg = self.field.regularization()
        if reg is not None:
            terms["regularization"] = reg
            loss = loss + reg
        if not bool(torch.isfinite(loss)):
            return self._skip_nonfinite(step, terms)
        self.nonfinite_in_row = 0
        # Lightning writes logged values at the end of steps with (step + 1) % every == 0
        if (step + 1) % max(1, self.step_cfg.log_every) == 0:
            fine = levels[-1]
            opacity = torch.stack([fine[f"opacity_{k}"].mean() for k in ("t0", "t1", "ref")])
            terms["opacity"] = opacity.mean().detach()
            self.opacity_log.append((step + 1, float(terms["opacity"])))
            for k, v in terms.items():
                self.log(f"train/{k}", v.detach(), on_step=True, on_epoch=False)
            self.log("train/lr", self.trainer.optimizers[0].param_groups[0]["lr"],
                     on_step=True, on_epoch=False)
            for key, value in self.renderer.step_stats(3 * n_rays).items():
                self.log(f"train/{key}", value, on_step=True, on_epoch=False)
        return loss

    def _skip_nonfinite(self, step: int, terms: dict[str, Tensor]) -> None:
        self.nonfinite_in_row += 1
        self.nonfinite_total += 1
        bad = [k for k, v in terms.items() if not bool(torch.isfinite(v))]
        log.warning("step %d: non-finite loss (%s); step skipped (%d in a row)",
                    step, ", ".join(bad), self.nonfinite_in_row)
        self.log("train/nonfinite_steps", float(self.nonfinite_total), on_step=True,
                 on_epoch=False)
        if self.nonfinite_in_row >= self.step_cfg.max_nonfinite:
            ckpt = Path(self.trainer.default_root_dir) / "checkpoints" / "nonfinite-stop.ckpt"
            self.stop_reason = (f"{self.nonfinite_in_row} non-finite losses in a row at step "
                                f"{step} ({', '.join(bad)}); stopped, checkpoint {ckpt}")
            self.trainer.save_checkpoint(str(ckpt), weights_only=False)
            raise NonFiniteLossError(self.stop_reason)
        return None

    def train_dataloader(self) -> Any:
        """Steps are drawn in :meth:`training_step`; the loader only counts them."""
        return torch.utils.data.DataLoader(StepCounter(), batch_size=None)

    # ------------------------------------------------------------------ checkpoints
    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["eventrecon"] = {
            "field_class": field_class_name(self.field),
            "clip_scale": float(getattr(self.renderer, "clip_scale", 1.0)),
            "nonfinite_total": self.nonfinite_total,
            "opacity_log": list(self.opacity_log),
            "method_version": records.METHOD_VERSION,
            "data_id": self.data_id,
            "sizing": records.sizing_choice(),
        }

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        meta = checkpoint.get("eventrecon", {})
        mine = field_class_name(self.field)
        if meta.get("field_class", mine) != mine:  # build.inspect_checkpoint catches it first
            where = getattr(self._trainer, "ckpt_path", None) or "checkpoint"
            raise InputError(where, "eventrecon.field_class",
                             f"a checkpoint of {mine} (this run's model)", meta["field_class"])
        if hasattr(self.renderer, "clip_scale"):
            self.renderer.clip_scale = meta.get("clip_scale", self.renderer.clip_scale)
        self.nonfinite_total = meta.get("nonfinite_total", 0)
        step = int(checkpoint.get("global_step", 0))
        self.opacity_log = [(int(s), float(o)) for s, o in meta.get("opacity_log", [])
                            if int(s) <= step]
