"""A run, top to bottom: data → field → module → callbacks → logger → trainer → fit → evaluate.

``run(cfg, out_dir)`` is what ``train.py`` calls with the composed Hydra config. For each
segment of the scene (one for synthetic scenes, several overlapping ones for rig-like
and real scenes) it trains a fresh field in ``out_dir/seg<k>/`` (resuming from its
``last.ckpt`` when present), then renders the held-out views at every ground-truth time,
cross-fading segments, and writes ``metrics.json``. Objects are built by
:mod:`eventrecon.engine.build`, the data selected by :mod:`eventrecon.data.selection`, the
records written by :mod:`eventrecon.results.records`, the scoring done by
:mod:`eventrecon.evaluate`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import lightning as L
from omegaconf import DictConfig, OmegaConf

from eventrecon.common.errors import InputError
from eventrecon.common.files import remove_stale_temporaries
from eventrecon.common.locks import exclusive
from eventrecon.config.precision import run_precision
from eventrecon.data.batcher import Segment
from eventrecon.data.datamodule import SegmentDataModule
from eventrecon.data.properties import SceneProperties
from eventrecon.data.selection import heldout_split, training_split
from eventrecon.data.types import SplitData
from eventrecon.engine.build import (
    build_callbacks,
    build_logger,
    build_module,
    inspect_checkpoint,
    load_dataset,
    scene_properties,
)
from eventrecon.engine.callbacks import HeldOutMonitor
from eventrecon.engine.checkpointing import AtomicCheckpointIO
from eventrecon.engine.collapse import CollapseRule, collapse_reason
from eventrecon.engine.memory import peak_mb, reset_peak
from eventrecon.engine.module import EventNeRFModule
from eventrecon.engine.progress import Progress
from eventrecon.engine.run_folder import evaluate_models, run_device
from eventrecon.engine.run_keys import check_run_keys
from eventrecon.engine.segments import run_segments, run_window, segment_config, segment_steps
from eventrecon.results import records
from eventrecon.results.machine import machine_name

__all__ = ["run", "train_segment", "flat_hparams"]

log = logging.getLogger(__name__)


def flat_hparams(cfg: DictConfig) -> dict[str, Any]:
    """The run's config as flat ``section.key`` scalars (lists as text) for TensorBoard's
    HParams tab; the scene's object list and the Lightning passthrough are left out.

    >>> flat_hparams(OmegaConf.create({"seed": 1, "model": {"width": 64, "optim": {"lr": 1e-3}},
    ...                                "scene": {"objects": [1], "rgb_fps": 5}}))
    {'seed': 1, 'model.width': 64, 'model.optim.lr': 0.001, 'scene.rgb_fps': 5}
    """
    out: dict[str, Any] = {}

    def walk(node: Any, prefix: str) -> None:
        for key, value in node.items():
            name = f"{prefix}{key}"
            if name in ("scene.objects", "trainer.lightning", "hydra"):
                continue
            if isinstance(value, dict):
                walk(value, f"{name}.")
            elif isinstance(value, (list, tuple)):
                out[name] = str(value)
            else:
                out[name] = value

    walk(OmegaConf.to_container(cfg, resolve=True), "")
    return out


def _trainer(cfg: DictConfig, seg_dir: Path, callbacks: list, k: int) -> L.Trainer:
    """Lightning's trainer for one segment: checkpoints every ``checkpoint_every`` steps
    (atomically), the configured logger and the ``trainer.lightning`` passthrough."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    ckpt = ModelCheckpoint(dirpath=seg_dir / "checkpoints", save_last=True, save_top_k=0,
                           every_n_train_steps=cfg.trainer.checkpoint_every)
    logger = build_logger(cfg, seg_dir.parent, f"seg{k}")
    if logger:
        logger.log_hyperparams(flat_hparams(cfg))
    kwargs = OmegaConf.to_container(cfg.trainer.lightning, resolve=True)
    kwargs["precision"] = run_precision(cfg)
    return L.Trainer(max_steps=int(cfg.trainer.max_steps), default_root_dir=str(seg_dir),
                     logger=logger, callbacks=[ckpt, *callbacks, *build_callbacks(cfg)],
                     plugins=[AtomicCheckpointIO()], log_every_n_steps=cfg.trainer.log_every,
                     enable_model_summary=False, **kwargs)


def _resume_checkpoint(cfg: DictConfig, seg_dir: Path, module: EventNeRFModule,
                       k: int) -> str | None:
    """The checkpoint segment ``k`` resumes from (``ckpt_path``: ``last`` or a file), checked
    to be this backbone's and not trained past this run's budget; ``None`` to start fresh."""
    removed = remove_stale_temporaries(seg_dir / "checkpoints")
    if removed:
        log.info("segment %d: removed %d temporary file(s) of an interrupted checkpoint write",
                 k, len(removed))
    if cfg.ckpt_path == "last":
        last = seg_dir / "checkpoints" / "last.ckpt"
        ckpt = str(last) if last.exists() else None
    else:
        ckpt = str(cfg.ckpt_path) if cfg.ckpt_path else None
    if ckpt is None:
        return None
    info = inspect_checkpoint(ckpt, module.field)
    stale = records.stale_reason(info.meta, module.data_id)
    if cfg.ckpt_path == "last" and stale is not None:
        kept = Path(ckpt).with_name(f"last.{stale[0]}.ckpt")
        Path(ckpt).replace(kept)
        log.warning("segment %d: %s was %s: kept as %s, training starts afresh", k, ckpt,
                    stale[1], kept.name)
        return None
    max_steps = int(cfg.trainer.max_steps)
    if info.step > max_steps:
        raise InputError(ckpt, "global_step", f"at most this run's {max_steps} steps per segment "
                         "(a run trained longer: use a new output folder)", info.step)
    log.info("segment %d: resuming from %s (step %s)", k, ckpt, info.step)
    return ckpt


def train_segment(cfg: DictConfig, props: SceneProperties, train: SplitData,
                  heldout: SplitData | None, k: int, seg: Segment, out_dir: Path,
                  n_segments: int = 1, data_id: str | None = None
                  ) -> tuple[EventNeRFModule, float]:
    """Train (or resume) segment ``k`` for ``cfg.trainer.max_steps`` steps (a config from
    :func:`~eventrecon.engine.segments.segment_config`) on the dataset ``data_id``; returns the
    module and the segment's training seconds (a resumed segment counts the time before
    the interruption too)."""
    seg_dir = out_dir / f"seg{k}"
    L.seed_everything(cfg.seed + 1000 * k, workers=True, verbose=False)
    module = build_module(cfg, props, None, seg, k)
    module.data_id = data_id
    data = SegmentDataModule(train, seg, props.decay, props.bayer, cfg.data.neg_ratio)
    callbacks: list = []
    monitor = None
    if heldout is not None:  # first: its clock then counts the schedules' work as training
        monitor = HeldOutMonitor(heldout, seg, seg_dir, cfg.trainer.curve_every,
                                 cfg.trainer.eval_every, cfg.trainer.image_every,
                                 cfg.trainer.curve_pixels, cfg.render.chunk, cfg.seed)
        callbacks.append(monitor)
    callbacks += list(module.field.callbacks())
    callbacks += list(module.renderer.callbacks(cfg.seed + 1000 * k))
    callbacks.append(Progress(k, n_segments, cfg.trainer.get("progress", "auto"),
                              cfg.trainer.get("progress_every_s", 30.0), monitor))
    trainer = _trainer(cfg, seg_dir, callbacks, k)
    ckpt = _resume_checkpoint(cfg, seg_dir, module, k)
    t = time.perf_counter()
    trainer.fit(module, datamodule=data, ckpt_path=ckpt)
    if module.stop_reason is None:  # every rank: saving is a collective call under DDP
        trainer.save_checkpoint(str(seg_dir / "checkpoints" / "last.ckpt"), weights_only=False)
    wall = monitor.wall if monitor is not None else time.perf_counter() - t
    return module, wall


#: Final scores shown in TensorBoard (``final/<key>``), when the run has them.
FINAL_SCALARS: tuple[str, ...] = ("psnr", "ssim", "lpips", "lpips_vgg", "psnr_background",
                                  "gain_psnr", "psnr_subject", "ssim_subject",
                                  "gain_psnr_subject")


def _log_final(cfg: DictConfig, out_dir: Path, metrics: dict[str, Any]) -> None:
    """The held-out scores, full-frame and on the subject, as TensorBoard scalars of the
    run (``<out>/tb/final``, step = the run's total steps)."""
    if not cfg.logger or "TensorBoard" not in str(cfg.logger.get("_target_", "")):
        return
    from torch.utils.tensorboard import SummaryWriter

    with SummaryWriter(str(out_dir / "tb" / "final")) as w:
        for key in FINAL_SCALARS:
            if isinstance(metrics.get(key), (int, float)):
                w.add_scalar(f"final/{key}", float(metrics[key]), int(metrics.get("steps", 0)))
        w.add_scalar("final/collapsed", float(metrics.get("status") == "collapsed"),
                     int(metrics.get("steps", 0)))


def _global_rank() -> int:
    """This process's rank in a multi-GPU (DDP) run; 0 otherwise."""
    from lightning.pytorch.utilities.rank_zero import rank_zero_only

    return int(getattr(rank_zero_only, "rank", 0) or 0)


def run(cfg: DictConfig, out_dir: str | Path) -> dict[str, Any]:
    """Train every segment of the run and evaluate; returns (and saves) the metrics.

    Each segment trains ``segment_steps`` steps with the config of
    :func:`~eventrecon.engine.segments.segment_config` and records ``seg<k>/done.json``; a
    segment done with this budget is not trained again. With ``data.segment=k`` only
    segment ``k`` is trained; the job that completes the last missing segment of the
    folder evaluates the whole run, under a lock, once (a multirun over
    ``data.segment``, whose jobs share one folder, ends cross-faded).
    """
    check_run_keys(cfg)                          # a typo fails before any data work
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    device = run_device(cfg)
    reset_peak(cuda=device.type == "cuda")
    ds = load_dataset(cfg)
    if "train" not in ds.splits:
        raise InputError(ds.root, "train/", "a training split")
    props = scene_properties(cfg, ds)
    window = run_window(cfg)
    train = training_split(ds, cfg.data.views, cfg.data.fps, props.duration_s,
                           window or (0.0, 1000.0))
    heldout = heldout_split(ds)
    segments = run_segments(cfg, props.segments)
    if cfg.data.segment is not None and not 0 <= int(cfg.data.segment) < len(segments):
        raise InputError("config", "data.segment",
                         f"a segment index in [0, {len(segments) - 1}]", cfg.data.segment)
    todo = range(len(segments)) if cfg.data.segment is None else [int(cfg.data.segment)]
    if cfg.ckpt_path not in (None, "last") and len(todo) > 1:
        raise InputError("config", "ckpt_path", f"'last', or one checkpoint with data.segment=K "
                         f"(one file cannot resume {len(todo)} segments)", cfg.ckpt_path)
    data_id = Path(ds.root).name
    info = records.run_info(cfg, ds.meta, views=train.n_views,
                            fps=cfg.data.fps or props.rgb_fps, data_id=data_id)
    steps = segment_steps(cfg, len(segments))
    seg_cfg = segment_config(cfg, steps)
    log.info("run %s: %d training views, %d RGB frames, %d segment(s), %d steps each",
             info, train.n_views, len(train.frame_times), len(segments), steps)
    trained: dict[int, Any] = {}
    for k in todo:
        seg_dir = out_dir / f"seg{k}"
        if records.read_done(seg_dir, steps, current_method=True, data_id=data_id) is not None:
            log.info("segment %d: trained before (%s), not trained again", k,
                     seg_dir / records.DONE_FILE)
            continue
        module, wall = train_segment(seg_cfg, props, train, heldout, k, segments[k], out_dir,
                                     len(segments), data_id)
        if _global_rank() != 0:
            continue  # DDP: rank 0 records and evaluates
        records.write_done(seg_dir, steps, module.global_step, wall, module.nonfinite_total,
                           module.opacity_log, data_id)
        trained[k] = (module.field, module.renderer)
    if _global_rank() != 0:
        return {**info, "status": "ok", "error": None, "rank": _global_rank()}
    metrics: dict[str, Any] = {**info, "status": "ok", "error": None,
                               "max_steps": int(cfg.trainer.max_steps),
                               "steps_per_segment": steps,
                               "segments": [[s.start, s.end] for s in segments]}
    seg_dirs = [out_dir / f"seg{k}" for k in range(len(segments))]
    dones = [records.read_done(d, steps, current_method=True, data_id=data_id) for d in seg_dirs]
    if any(d is None for d in dones):
        missing = [k for k, d in enumerate(dones) if d is None]
        log.info("segments %s not trained yet: the run is evaluated when they are", missing)
        return {**metrics, "status": "partial", "missing_segments": missing}
    metrics.update({"steps": sum(int(d["steps"]) for d in dones),
                    "wall_s": sum(float(d["wall_s"]) for d in dones),
                    "nonfinite_steps": sum(int(d["nonfinite_steps"]) for d in dones)})
    metrics["sec_per_it"] = metrics["wall_s"] / max(metrics["steps"], 1)
    with exclusive(out_dir / ".evaluate.lock"):  # parallel segment jobs: evaluate once
        previous = records.finished_metrics(out_dir / records.METRICS_FILE,
                                            metrics["max_steps"], cfg.evaluate, metrics["steps"],
                                            data_id)
        if previous is not None:
            return previous
        rows = records.stitch_curves(seg_dirs)
        if rows:
            records.write_curve(out_dir / records.CURVE_FILE, rows)
        if cfg.evaluate and heldout is not None:
            metrics.update(evaluate_models(seg_cfg, props, heldout, segments, trained, out_dir,
                                           device, window))
        reason = collapse_reason([d.get("opacity_log", []) for d in dones], metrics.get("psnr"),
                                 metrics.get("psnr_background"),
                                 CollapseRule(**cfg.trainer.get("collapse", {})),
                                 metrics.get("psnr_subject"),
                                 metrics.get("psnr_background_subject"))
        if reason is not None:
            metrics.update(status="collapsed", collapse_reason=reason)
            log.warning("run collapsed to the empty field: %s", reason)
        _log_final(cfg, out_dir, metrics)
        metrics["peak_mem_mb"] = peak_mb(cuda=device.type == "cuda")
        metrics["machine"] = machine_name(cuda=device.type == "cuda")
        metrics["total_s"] = time.perf_counter() - t_start
        records.write_metrics(out_dir, metrics)
    return metrics
