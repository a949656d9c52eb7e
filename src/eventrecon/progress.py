"""Where a run is and when it will end: a progress bar on a terminal, log lines elsewhere.

One callback per segment (:class:`Progress`) reports, for segment ``k`` of ``K``: the
step out of the segment's steps, the training loss, seconds per step (over the last
reports), the time left and the latest held-out PSNR (the monitor's cheap curve point).
On a terminal it draws a ``tqdm`` bar; without one (CI, files, SLURM, sweeps under joblib)
it logs one plain line about every ``every_s`` seconds — no carriage-return fragments:

    segment 1/1  step 400/1000 (40%)  loss 0.2081  0.101 s/it  eta 1m01s  psnr 24.31 dB

``mode``: ``auto`` (a bar when stderr is a terminal, else lines), ``bar``, ``log`` or
``none``. :class:`TaskProgress` does the same for long work outside training
(full-image evaluation, simulation).
"""

from __future__ import annotations

import logging
import math
import sys
import time
from typing import Any

import lightning.pytorch as pl

__all__ = ["Progress", "TaskProgress", "format_seconds", "progress_mode"]

log = logging.getLogger("eventrecon.progress")


def format_seconds(s: float) -> str:
    """``3725 -> '1h02m'``, ``61 -> '1m01s'``, ``5.2 -> '5s'``.

    >>> format_seconds(3725), format_seconds(61), format_seconds(5.2), format_seconds(float("nan"))
    ('1h02m', '1m01s', '5s', '?')
    """
    if not math.isfinite(s):
        return "?"
    s = max(0.0, s)
    if s >= 3600:
        return f"{int(s // 3600)}h{int(s % 3600 // 60):02d}m"
    if s >= 60:
        return f"{int(s // 60)}m{int(s % 60):02d}s"
    return f"{s:.0f}s"


def progress_mode(mode: str) -> str:
    """``bar`` or ``log`` for ``auto`` (by whether stderr is a terminal), else ``mode``."""
    if mode == "auto":
        return "bar" if sys.stderr.isatty() else "log"
    if mode not in ("bar", "log", "none"):
        from eventrecon.errors import InputError

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


class TaskProgress:
    """Progress of a counted task outside training: a line about every ``every_s``
    seconds (``done/total``, rate, time left), or nothing for short tasks.

    >>> p = TaskProgress("evaluation", 3, every_s=0.0)
    >>> p.step(); p.step(); p.step()
    """

    def __init__(self, what: str, total: int, every_s: float = 30.0) -> None:
        self.what, self.total, self.every_s = what, int(total), float(every_s)
        self.done = 0
        self._t0 = self._last = time.perf_counter()

    def step(self, n: int = 1) -> None:
        """``n`` more units done; log a line when one is due."""
        self.done += n
        now = time.perf_counter()
        if now - self._last < self.every_s and self.done < self.total:
            return
        self._last = now
        rate = (now - self._t0) / max(self.done, 1)
        if self.done < self.total or now - self._t0 >= self.every_s:
            log.info("%s: %d/%d (%.0f%%)  %.2f s each  eta %s", self.what, self.done,
                     self.total, 100.0 * self.done / max(self.total, 1), rate,
                     format_seconds((self.total - self.done) * rate))
