"""Where a run is and when it will end: a progress bar on a terminal, log lines elsewhere.

One callback per segment (:class:`Progress`) reports, for segment ``k`` of ``K``: the
step out of the segment's steps, the training loss, seconds per step (over the last
reports), the time left and the latest held-out PSNR (the monitor's cheap curve point).
On a terminal it draws a ``tqdm`` bar; without one (CI, files, SLURM, sweeps under joblib)
it logs one plain line about every ``every_s`` seconds — no carriage-return fragments:

    segment 1/1  step 400/1000 (40%)  loss 0.2081  0.101 s/it  eta 1m01s  psnr 24.31 dB

``mode``: ``auto`` (a bar when stderr is a terminal, else lines), ``bar``, ``log`` or
``none``. Long work outside training (full-image evaluation, simulation, reading a
dataset) reports through :class:`eventrecon.common.progress.TaskProgress`.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from typing import Any

import lightning.pytorch as pl

from eventrecon.common.progress import format_seconds

__all__ = ["Progress", "progress_mode"]

log = logging.getLogger("eventrecon.engine.progress")


def progress_mode(mode: str) -> str:
    """``bar`` or ``log`` for ``auto`` (by whether stderr is a terminal), else ``mode``."""
    if mode == "auto":
        return "bar" if sys.stderr.isatty() else "log"
    if mode not in ("bar", "log", "none"):
        from eventrecon.common.errors import InputError

        raise InputError("config", "trainer.progress", "auto, bar, log or none", mode)
    return mode


class Progress(pl.Callback):
    """Training progress of segment ``k`` of ``n_segments`` (module docstring).

    Args:
        segment, n_segments: which segment (0-based) of how many.
        mode: ``auto``, ``bar``, ``log`` or ``none``.
        every_s: seconds between log lines (``log`` mode).
        monitor: an object with a ``last_psnr`` attribute (the held-out monitor), or None.
    """

    def __init__(self, segment: int, n_segments: int, mode: str = "auto",
                 every_s: float = 30.0, monitor: Any = None) -> None:
        super().__init__()
        self.label = f"segment {segment + 1}/{n_segments}"
        self.mode = progress_mode(mode)
        self.every_s = float(every_s)
        self.monitor = monitor
        self.bar: Any = None
        self._t0 = self._last_line = 0.0
        self._step0 = 0
        self._loss = math.nan

    def _fields(self, step: int, total: int) -> dict[str, str]:
        done = step - self._step0
        rate = (time.perf_counter() - self._t0) / done if done > 0 else math.nan
        psnr = getattr(self.monitor, "last_psnr", None)
        return {"loss": f"{self._loss:.4f}", "s/it": f"{rate:.3f}",
                "eta": format_seconds((total - step) * rate),
                "psnr": "—" if psnr is None else f"{psnr:.2f} dB"}

    def line(self, step: int, total: int) -> str:
        """The log line at ``step`` of ``total``."""
        f = self._fields(step, total)
        pct = 100.0 * step / max(total, 1)
        return (f"{self.label}  step {step}/{total} ({pct:.0f}%)  loss {f['loss']}  "
                f"{f['s/it']} s/it  eta {f['eta']}  psnr {f['psnr']}")

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self.mode == "none" or not trainer.is_global_zero:
            return
        self._t0 = self._last_line = time.perf_counter()
        self._step0 = int(trainer.global_step)
        if self.mode == "bar":
            from tqdm.auto import tqdm

            self.bar = tqdm(total=int(trainer.max_steps), initial=self._step0, desc=self.label,
                            dynamic_ncols=True, leave=True, file=sys.stderr)

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule,
                           outputs: Any, batch: Any, batch_idx: int) -> None:
        if self.mode == "none" or not trainer.is_global_zero:
            return
        step, total = int(trainer.global_step), int(trainer.max_steps)
        now = time.perf_counter()
        due = now - self._last_line >= (self.every_s if self.mode == "log" else 0.5)
        if not due and step != total:
            if self.bar is not None:
                self.bar.update(step - self.bar.n)
            return
        loss = outputs.get("loss") if isinstance(outputs, dict) else outputs
        if loss is not None:
            self._loss = float(loss)
        self._last_line = now
        if self.bar is not None:
            self.bar.update(step - self.bar.n)
            f = self._fields(step, total)
            self.bar.set_postfix(loss=f["loss"], psnr=f["psnr"], refresh=False)
        else:
            log.info("%s", self.line(step, total))

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None
