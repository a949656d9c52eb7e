"""The parts of ``bench_zoo``: a training run capped in training seconds, and the
measurements made afterwards on its trained field.

- :func:`compose_run` builds the run's config (``scale=cpu`` or ``trainer=paper``) with the
  backbone's warm-up schedules frozen to what the preset resolves them to, a huge
  ``max_steps`` and a :class:`BudgetStop` callback that ends the run at the last budget;
- :class:`BudgetStop` counts the occupancy-grid updates as training time, puts a held-out
  point on the curve just before each budget and stops the run;
- :func:`time_render` and :func:`time_steps` time the trained field: 346×260 images, and
  real training steps against the bare field step on the very samples each step sent.
"""

from __future__ import annotations

import copy
import json
import logging
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra import compose, initialize_config_dir
from omegaconf import DictConfig, OmegaConf, open_dict
from torch import Tensor

from benchmarks.bench_image import time_images
from eventrecon.engine.callbacks import HeldOutMonitor
from eventrecon.engine.losses import total_loss
from eventrecon.engine.module import EventNeRFModule, adamw_fused, step_generator

log = logging.getLogger("benchmarks.zoo")
CONF = str(Path(__file__).resolve().parents[1] / "conf")
#: ``max_steps`` of a budgeted run: never reached, the budget ends the run.
HUGE_STEPS = 10**8
STATS_FILE = "zoo_budget.json"


def sync(device: torch.device | str) -> None:
    """Wait for the device (CUDA timings); nothing on the CPU."""
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def compose_run(overrides: Sequence[str], budgets: Sequence[float], preset: str,
                data_dir: str, curve_every: int, safety_s: float) -> DictConfig:
    """The config of one budgeted run.

    ``preset`` is ``cpu`` (``scale=cpu``: its 256 rays, 32 + 32 samples, CPU sizes and
    schedules compressed to its 1000 steps) or ``paper`` (``trainer=paper``: 1024 rays,
    64 + 128 samples, the configs' own sizes, the paper's schedules). The model's
    ``${paper_steps:N}`` schedules are resolved *before* ``max_steps`` is raised to
    :data:`HUGE_STEPS`, so they keep the preset's values. No logger, checkpoints only at
    the end, cheap held-out points every ``curve_every`` steps, no full evaluation before
    the end; Lightning's ``max_time`` = ``safety_s`` in case the budget callback never
    fires.
    """
    base = ["scale=cpu"] if preset == "cpu" else ["trainer=paper"]
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(config_name="config", overrides=[
            *base, *overrides, f"data_dir={data_dir}", "logger=none", "trainer.progress=none",
            "evaluate=false", f"trainer.curve_every={curve_every}", "trainer.eval_every=0",
            "trainer.image_every=0", f"trainer.checkpoint_every={HUGE_STEPS}"])
    model = OmegaConf.to_container(cfg.model, resolve=True)
    with open_dict(cfg):
        cfg.model = model
        cfg.trainer.max_steps = HUGE_STEPS
        cfg.trainer.lightning.max_time = {"seconds": int(safety_s)}
        cfg.trainer.callbacks = {"zoo_budget": {
            "_target_": f"{__name__}.BudgetStop", "budgets": [float(b) for b in budgets]}}
    return cfg


class BudgetStop(L.Callback):
    """Ends a run after ``max(budgets)`` seconds of training (the held-out monitor's clock).

    - The occupancy grid's updates (run by ``OccupancyUpdate`` before the monitor starts
      its per-step clock, so the library's ``curve.csv`` leaves them out) are timed and
      added to the monitor's clock: here they count as training time.
    - When the next step could end past a budget (the current clock plus twice the
      longest of the last 8 steps, update time left out, plus the last update's seconds
      when the next step starts with one), a cheap held-out point is put on the curve
      now, so the curve has a row a step or two before every budget; at the last budget
      the run stops.
    - At the end, ``zoo_budget.json`` in the segment's folder holds the seconds and the
      number of the timed updates.
    """

    def __init__(self, budgets: Sequence[float]) -> None:
        super().__init__()
        self.budgets = sorted(float(b) for b in budgets)
        self.todo = list(self.budgets)
        self.monitor: HeldOutMonitor | None = None
        self.every = 0  # steps between grid updates (0: no grid)
        self.pending = 0.0  # update seconds not yet added to the monitor's clock
        self.this_update = 0.0  # update seconds of the current step
        self.update_s: list[float] = []
        self.deltas: list[float] = []
        self.last_wall = 0.0

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.monitor = next((c for c in trainer.callbacks if isinstance(c, HeldOutMonitor)),
                            None)
        if self.monitor is None:
            raise RuntimeError("BudgetStop needs the run's HeldOutMonitor (a held-out split)")
        grid = getattr(pl_module.renderer, "occupancy", None)
        if grid is not None:
            self.every = int(grid.every)
            update = grid.update

            def timed(*args: Any, **kwargs: Any) -> int:
                sync(pl_module.device)
                t0 = time.perf_counter()
                out = update(*args, **kwargs)
                sync(pl_module.device)
                self.pending += time.perf_counter() - t0
                self.update_s.append(time.perf_counter() - t0)
                return out

            grid.update = timed

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule,
                             batch: Any, batch_idx: int) -> None:
        self.this_update, self.pending = self.pending, 0.0
        if self.monitor is not None:
            self.monitor.wall += self.this_update

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule,
                           outputs: Any, batch: Any, batch_idx: int) -> None:
        mon = self.monitor
        if mon is None:
            return
        self.deltas = [*self.deltas[-7:], mon.wall - self.last_wall - self.this_update]
        self.last_wall = mon.wall
        step = int(trainer.global_step)  # the next step's index
        next_update = (self.update_s[-1] if self.every and self.update_s
                       and step % self.every == 0 else 0.0)
        margin = 2.0 * max(self.deltas) + next_update
        logged = mon.curve_every > 0 and step % mon.curve_every == 0
        while self.todo and mon.wall + margin > self.todo[0]:
            if not logged:
                mon.evaluate(trainer, pl_module, full=False)
                logged = True
            self.todo.pop(0)
        if not self.todo:
            trainer.should_stop = True

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        out = Path(trainer.default_root_dir) / STATS_FILE
        out.write_text(json.dumps({"update_s": sum(self.update_s),
                                   "updates": len(self.update_s),
                                   "wall_s": self.monitor.wall if self.monitor else None,
                                   "steps": int(trainer.global_step)}))


class SampleCounter:
    """A forward hook on a field that records its inputs while :attr:`on`."""

    def __init__(self, field: torch.nn.Module) -> None:
        self.on = False
        self.calls: list[tuple[Tensor, Tensor]] = []
        self.handle = field.register_forward_hook(self._hook)

    def _hook(self, module: torch.nn.Module, inputs: tuple, output: Any) -> None:
        if self.on:
            self.calls.append((inputs[0].detach(), inputs[1].detach()))

    def take(self) -> list[tuple[Tensor, Tensor]]:
        """The recorded calls, cleared."""
        calls, self.calls = self.calls, []
        return calls


def time_render(module: EventNeRFModule, cfg: DictConfig, n_images: int, width: int = 346,
                height: int = 260) -> dict[str, float]:
    """Median seconds of ``renderer.render_image`` of a ``width``×``height`` image and the
    field samples per pixel it took (:func:`benchmarks.bench_image.time_images`: the
    scene's rig, no warm-up image); the field is left in training mode."""
    try:
        row = time_images(module.field, module.renderer, dict(cfg.scene.get("rig") or {}),
                          n_images, width, height, warmup=0)
    finally:
        module.field.train()
    return {"render_s": row["median_s"], "render_samples_per_px": row["samples_per_px"]}


def _update_grid(module: EventNeRFModule, seed: int, step: int) -> float:
    """One occupancy update as ``OccupancyUpdate`` makes it at ``step``; its seconds."""
    grid, field = module.renderer.occupancy, module.field
    gen = torch.Generator().manual_seed(seed * 1_000_003 + step)
    field.eval()
    sync(module.device)
    t0 = time.perf_counter()
    grid.update(lambda x, t: module.renderer.masked_density(field, x, t), gen)
    sync(module.device)
    field.train()
    return time.perf_counter() - t0


def time_steps(module: EventNeRFModule, step0: int, warmup: int, reps: int, seed: int
               ) -> dict[str, float]:
    """Real training steps of the trained module against the bare field step.

    A *real* step is ``EventNeRFModule.training_step`` without Lightning: batch, the three
    renders, the losses, the field's regulariser, backward and AdamW, with the occupancy
    grid updated every ``grid.every`` steps as in a run (those updates are timed apart
    and reported per step, amortised). A forward hook records the inputs of every field
    call of a real step; the *bare* step replays exactly those calls (same points, same
    batch sizes) on a copy of the field with its own optimiser (so the real field is
    not disturbed): forward, ``mean σ + mean rgb`` per call, backward (``field_s``), then
    the AdamW step (``optim_s``). ``rest_s = real_s − field_s − optim_s`` is what the
    step spends outside the field: sampling, compositing, losses and their backward.
    Real and bare steps alternate (same background load); medians over ``reps`` after
    ``warmup`` steps. ``samples_per_ray`` = samples the renderer sent to the field in a
    real step (:attr:`Renderer.field_inputs`, without the padded rows) / (3 · n_rays).
    """
    field, cfg_s = module.field, module.step_cfg
    field.train()
    opt = module.configure_optimizers()
    bare_field = copy.deepcopy(field)
    bare_groups = bare_field.param_groups(cfg_s.lr)
    bare_opt = torch.optim.AdamW(bare_groups, lr=cfg_s.lr, weight_decay=cfg_s.weight_decay,
                                 betas=cfg_s.betas, eps=cfg_s.eps,
                                 fused=adamw_fused(bare_groups))   # as the module's
    grid = module.renderer.occupancy
    counter = SampleCounter(field)
    dev = module.device

    def optimise(loss: Tensor, f: torch.nn.Module, o: torch.optim.Optimizer,
                 after_backward: Callable[[], None] | None = None) -> None:
        reg = f.regularization()
        if reg is not None:
            loss = loss + reg
        o.zero_grad(set_to_none=True)
        loss.backward()
        if after_backward is not None:
            after_backward()
        o.step()

    def real(s: int) -> None:
        gen = step_generator(cfg_s.seed, s)
        batch = module.batcher.sample(cfg_s.n_rays, gen)
        levels = module.render_three(batch, gen)
        optimise(total_loss(levels, batch, module.loss_cfg, s)["loss"], field, opt)

    def bare(calls: list[tuple[Tensor, Tensor]]) -> tuple[float, float]:
        marks: list[float] = []
        t0 = time.perf_counter()
        loss = torch.zeros((), device=dev)
        for xyz, t in calls:
            sigma, rgb = bare_field(xyz, t)
            loss = loss + sigma.mean() + rgb.mean()

        def mark() -> None:
            sync(dev)
            marks.append(time.perf_counter())

        optimise(loss, bare_field, bare_opt, mark)
        sync(dev)
        return marks[0] - t0, time.perf_counter() - marks[0]

    rows: dict[str, list[float]] = {k: [] for k in ("real", "field", "optim", "samples")}
    updates: list[float] = []
    try:
        for i in range(warmup + reps):
            s = step0 + i
            if grid is not None:  # as OccupancyUpdate does at the start of step s
                grid.active = s >= grid.start_step
                if s % grid.every == 0:
                    updates.append(_update_grid(module, seed, s))
            counter.on = True
            sync(dev)
            t0 = time.perf_counter()
            real(s)
            sync(dev)
            real_s = time.perf_counter() - t0
            counter.on = False
            calls = counter.take()
            field_s, optim_s = bare(calls)
            if i >= warmup:
                rows["real"].append(real_s)
                rows["field"].append(field_s)
                rows["optim"].append(optim_s)
                # the renderer's count: its samples, not the padded rows the field saw
                rows["samples"].append(module.renderer.field_inputs / (3 * cfg_s.n_rays))
    finally:
        counter.handle.remove()
    if grid is not None and not updates:
        updates.append(_update_grid(module, seed, step0 + warmup + reps))
    med = {k: statistics.median(v) for k, v in rows.items()}
    return {"real_s": med["real"], "field_s": med["field"], "optim_s": med["optim"],
            "rest_s": med["real"] - med["field"] - med["optim"],
            "samples_per_ray": statistics.mean(rows["samples"]),
            "update_s_per_step": (statistics.median(updates) / grid.every) if updates else 0.0}
