"""A run, top to bottom: data → field → module → callbacks → logger → trainer → fit → evaluate.

``run(cfg, out_dir)`` is what ``train.py`` calls with the composed Hydra config. For each
segment of the scene (one for synthetic scenes, several overlapping ones for rig-like
and real scenes, one when ``loss.multiseg=false``) it trains a fresh field in
``out_dir/seg<k>/`` (resuming from its ``last.ckpt`` when present), then renders the
held-out views at every ground-truth time, cross-fading segments, and writes
``metrics.json``.
"""

from __future__ import annotations

import importlib
import json
import logging
import resource
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf

from eventrecon.checkpointing import AtomicCheckpointIO, atomic_write_json
from eventrecon.data.batcher import RayBatcher, Segment
from eventrecon.data.types import Dataset, SplitData
from eventrecon.errors import InputError
from eventrecon.fields.base import Field
from eventrecon.losses import LossConfig
from eventrecon.module import EventNeRFModule, StepConfig, field_class_name
from eventrecon.render.volume import Renderer
from eventrecon.segments import resolve_segments

__all__ = ["run", "load_dataset", "build_field", "build_renderer", "select_views",
           "select_fps", "evaluate_run", "run_info", "planned_run_info", "check_checkpoint"]

log = logging.getLogger(__name__)

DEFAULT_CYLINDER = {"radius": 0.5, "y_min": -0.75, "y_max": 0.25}
NO_CLIPPING = {"radius": 1.0, "y_min": -1.0, "y_max": 1.0}


# ---------------------------------------------------------------------------- data
def load_dataset(cfg: DictConfig) -> Dataset:
    """The dataset of a run: ``data.root`` if given, else the simulated ``scene``."""
    from eventrecon.data.layout import read_dataset

    if cfg.data.root:
        return read_dataset(Path(cfg.data.root))
    from eventrecon.sim.pipeline import ensure_dataset

    root = ensure_dataset(cfg.scene, cfg.data_dir)
    return read_dataset(root)


def select_views(split: SplitData, n: int | None) -> SplitData:
    """An evenly spread subset of ``n`` views of the ring (all when ``n`` is None)."""
    V = split.n_views
    if n is None or n == V:
        return split
    if not 1 <= n <= V:
        raise InputError("config", "data.views", f"an integer in [1, {V}] (views in the dataset)", n)
    idx = sorted({int(i) for i in np.floor(np.arange(n) * V / n)})
    return replace(
        split, cameras=split.cameras.select(idx),
        events=None if split.events is None else [split.events[i] for i in idx],
        frames=split.frames[:, idx],
        background=None if split.background is None else split.background[idx],
        masks=None if split.masks is None else split.masks[:, idx])


def select_fps(split: SplitData, fps: float | None, duration_s: float) -> SplitData:
    """Keep the frames nearest to a ``fps`` grid ``k · 1000 / (fps · duration_s)``."""
    if fps is None:
        return split
    if fps <= 0:
        raise InputError("config", "data.fps", "a positive frame rate", fps)
    times = np.asarray(split.frame_times, dtype=np.float64)
    step = 1000.0 / (fps * duration_s)
    grid = np.arange(0.0, 1000.0 + 1e-9, step)
    keep = sorted({int(np.argmin(np.abs(times - g))) for g in grid})
    if len(times) > 1 and step < float(np.min(np.diff(times))) - 1e-6:
        native = 1000.0 / (float(np.min(np.diff(times))) * duration_s)
        raise InputError("config", "data.fps", f"at most the dataset's {native:g} FPS", fps)
    return replace(split, frame_times=times[keep], frames=split.frames[keep],
                   masks=None if split.masks is None else split.masks[keep])


# ---------------------------------------------------------------------------- model
def build_field(model_cfg: DictConfig) -> Field:
    """Instantiate ``cfg.model`` (its ``_target_``; ``optim`` holds lr / weight decay)."""
    kwargs = OmegaConf.to_container(model_cfg, resolve=True)
    assert isinstance(kwargs, dict)
    target = kwargs.pop("_target_", None)
    kwargs.pop("optim", None)
    kwargs.pop("name", None)
    expect = "an importable Field class (e.g. eventrecon.fields.nerf.NeRFField)"
    if not target:
        raise InputError("config", "model._target_", expect, "nothing")
    module, _, name = str(target).rpartition(".")
    try:
        cls = getattr(importlib.import_module(module), name) if module else None
    except (ImportError, AttributeError) as e:
        raise InputError("config", "model._target_", expect,
                         f"{target} ({type(e).__name__}: {e})") from None
    if not (isinstance(cls, type) and issubclass(cls, Field)):
        raise InputError("config", "model._target_", expect, target)
    try:
        return cls(**kwargs)
    except TypeError as e:  # an argument the class does not take (`+model.foo=1`)
        raise InputError("config", "model", f"the arguments of {target}", str(e)) from None


def build_renderer(cfg: DictConfig, meta: dict) -> Renderer:
    """The renderer with the run's samples and clipping cylinder."""
    cyl = dict(DEFAULT_CYLINDER)
    cyl.update(meta.get("cylinder") or {})
    if not cfg.loss.clipping:
        cyl = dict(NO_CLIPPING)
    return Renderer(n_coarse=cfg.trainer.n_coarse, n_fine=cfg.trainer.n_fine,
                    chunk=cfg.trainer.chunk, **cyl)


def loss_config(cfg: DictConfig, meta: dict) -> LossConfig:
    lc = cfg.loss
    return LossConfig(w_event=lc.w_event, w_acc=lc.w_acc, w_rgb=lc.w_rgb,
                      lam_sparsity=lc.lam_sparsity, sparsity_ramp=lc.sparsity_ramp,
                      eps=float(meta.get("tonemap_eps", 1e-2)),
                      theta=float(meta.get("threshold", 0.5)))


def run_info(cfg: DictConfig, meta: dict, views: int | None = None,
             fps: float | None = None) -> dict[str, Any]:
    """What identifies a run in the reports (experiment, scene, model, loss, views, fps)."""
    choices = {}
    try:
        from hydra.core.hydra_config import HydraConfig
        choices = dict(HydraConfig.get().runtime.choices)
    except Exception:  # noqa: BLE001 - outside a Hydra app
        pass
    return {"scene": meta.get("scene_name") or cfg.scene.get("name", "custom"),
            "model": cfg.model.get("name") or choices.get("model") or str(cfg.model._target_),
            "loss": cfg.loss.get("name", choices.get("loss", "full")),
            "views": views if views is not None else cfg.data.views,
            "fps": fps if fps is not None else (cfg.data.fps or meta.get("rgb_fps")),
            "experiment": cfg.get("sweep_name"), "tag": cfg.get("tag")}


def planned_run_info(cfg: DictConfig) -> dict[str, Any]:
    """:func:`run_info` of a run that may have failed before reading its data.

    For the ``status: failed`` record of a sweep job: the identity is what the finished
    run would have written (same ``views`` and ``fps``), so the report puts the failure in
    the right cell. Reads only the dataset's ``meta.json`` and counts its training poses
    when the dataset is on disk; otherwise falls back to the scene config.
    """
    root: Path | None = None
    meta: dict = {}
    try:
        if cfg.data.root:
            root = Path(cfg.data.root)
        else:
            from eventrecon.sim.pipeline import dataset_path

            root = dataset_path(cfg.scene, cfg.data_dir)
        meta = json.loads((root / "meta.json").read_text())
    except Exception:  # noqa: BLE001 - best effort: the run may have failed on this very input
        if not cfg.data.root:
            meta = {"rgb_fps": cfg.scene.get("rgb_fps")}
    views = cfg.data.views
    if views is None and root is not None:
        views = len(list((root / "train" / "pose").glob("*.txt"))) or None
    if views is None and not cfg.data.root:
        views = (cfg.scene.get("rig") or {}).get("n_train")
    return run_info(cfg, meta, views=views, fps=cfg.data.fps or meta.get("rgb_fps"))


def merge_curves(seg_dirs: list[Path], out: Path) -> None:
    """One ``curve.csv`` for the run: segment rows in order, steps made cumulative."""
    import csv

    rows, offset = [], 0
    for d in seg_dirs:
        path = d / "curve.csv"
        if not path.exists():
            continue
        with path.open(newline="") as f:
            seg_rows = list(csv.DictReader(f))
        for r in seg_rows:
            r["step"] = str(int(r["step"]) + offset)
        rows += seg_rows
        offset = int(rows[-1]["step"]) if rows else offset
    if rows:
        with out.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)


# ---------------------------------------------------------------------------- training
def _trainer(cfg: DictConfig, seg_dir: Path, callbacks: list, k: int) -> L.Trainer:
    from lightning.pytorch.callbacks import ModelCheckpoint

    ckpt = ModelCheckpoint(dirpath=seg_dir / "checkpoints", save_last=True, save_top_k=0,
                           every_n_train_steps=cfg.trainer.checkpoint_every)
    logger: Any = False
    if cfg.logger and cfg.logger.get("_target_"):
        lg = dict(OmegaConf.to_container(cfg.logger, resolve=True))
        logger = get_class(lg.pop("_target_"))(save_dir=str(seg_dir.parent), version=f"seg{k}", **lg)
    kwargs = OmegaConf.to_container(cfg.trainer.lightning, resolve=True)
    return L.Trainer(max_steps=cfg.trainer.max_steps, default_root_dir=str(seg_dir),
                     logger=logger, callbacks=[ckpt, *callbacks],
                     plugins=[AtomicCheckpointIO()], log_every_n_steps=cfg.trainer.log_every,
                     enable_model_summary=False, **kwargs)


def train_segment(cfg: DictConfig, ds: Dataset, train: SplitData, heldout: SplitData | None,
                  k: int, seg: Segment, out_dir: Path, wall_offset: float = 0.0
                  ) -> tuple[EventNeRFModule, float]:
    """Train (or resume) segment ``k``; returns the module and its training seconds."""
    from eventrecon.callbacks import HeldOutMonitor

    meta = ds.meta
    seg_dir = out_dir / f"seg{k}"
    L.seed_everything(cfg.seed + 1000 * k, workers=True, verbose=False)
    field = build_field(cfg.model)
    renderer = build_renderer(cfg, meta)
    decay = cfg.loss.decay if cfg.loss.decay is not None else float(meta.get("decay", 1.0))
    device = "cuda" if cfg.trainer.lightning.accelerator in ("gpu", "cuda") else "cpu"
    batcher = RayBatcher(train, seg, decay=decay, bayer=bool(meta.get("bayer", False)),
                         neg_ratio=cfg.data.neg_ratio, device=device)
    optim = cfg.model.get("optim", {}) or {}
    lr = cfg.trainer.lr if cfg.trainer.lr is not None else optim.get("lr", 1e-3)
    step = StepConfig(n_rays=cfg.trainer.n_rays, lr=float(lr),
                      weight_decay=float(optim.get("weight_decay", 0.0)),
                      max_nonfinite=cfg.trainer.max_nonfinite, log_every=cfg.trainer.log_every,
                      seed=cfg.seed + 1000 * k)
    module = EventNeRFModule(field, renderer, batcher, loss_config(cfg, meta), step)
    callbacks = list(field.callbacks())
    monitor = None
    if heldout is not None:
        monitor = HeldOutMonitor(heldout, seg, seg_dir, cfg.trainer.curve_every,
                                 cfg.trainer.eval_every, cfg.trainer.image_every,
                                 cfg.trainer.curve_pixels, cfg.trainer.chunk, cfg.seed,
                                 wall_offset)
        callbacks.append(monitor)
    trainer = _trainer(cfg, seg_dir, callbacks, k)
    ckpt = None
    if cfg.ckpt_path == "last":
        last = seg_dir / "checkpoints" / "last.ckpt"
        ckpt = str(last) if last.exists() else None
    elif cfg.ckpt_path:
        ckpt = str(cfg.ckpt_path)
    if ckpt:
        check_checkpoint(ckpt, field)
        log.info("segment %d: resuming from %s", k, ckpt)
    t = time.perf_counter()
    trainer.fit(module, ckpt_path=ckpt)
    wall = monitor.wall - wall_offset if monitor is not None else time.perf_counter() - t
    return module, wall


def check_checkpoint(path: str | Path, field: Field) -> None:
    """Raise :class:`InputError` unless ``path`` is a readable checkpoint of ``field``'s class.

    Runs before ``trainer.fit(ckpt_path=...)`` so that a missing, corrupt or foreign
    checkpoint (another backbone's) is one line naming the file, not a traceback from
    Lightning's state-dict loading. The file is memory-mapped, not read.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("config", "ckpt_path", "an existing checkpoint file or 'last'", path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=False, mmap=True)
    except Exception as e:  # noqa: BLE001 - zip, pickle and I/O errors alike
        first = str(e).splitlines()[0] if str(e) else ""
        raise InputError(path, "<file>", "a checkpoint readable by torch.load",
                         f"{type(e).__name__}: {first}") from None
    if not isinstance(state, dict) or "state_dict" not in state:
        raise InputError(path, "state_dict", "a Lightning checkpoint", "missing")
    mine = field_class_name(field)
    theirs = (state.get("eventrecon") or {}).get("field_class", mine)
    if theirs != mine:
        raise InputError(path, "eventrecon.field_class",
                         f"a checkpoint of {mine} (this run's model)", theirs)


def _peak_mem_mb() -> float:
    if torch.cuda.is_available():
        return torch.cuda.max_memory_allocated() / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run(cfg: DictConfig, out_dir: str | Path) -> dict[str, Any]:
    """Train every segment of the run and evaluate; returns (and saves) the metrics."""
    from eventrecon.evaluate import evaluate_heldout, render_heldout, write_renders

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    ds = load_dataset(cfg)
    meta = ds.meta
    if "train" not in ds.splits:
        raise InputError(ds.root, "train/", "a training split")
    train = select_views(ds.splits["train"], cfg.data.views)
    train = select_fps(train, cfg.data.fps, float(meta.get("duration_s", 1.0)))
    heldout = ds.splits.get("validation")
    segments = resolve_segments(meta.get("segments"), cfg.loss.multiseg)
    todo = range(len(segments)) if cfg.data.segment is None else [int(cfg.data.segment)]
    info = run_info(cfg, meta, views=train.n_views,
                    fps=cfg.data.fps or meta.get("rgb_fps"))
    log.info("run %s: %d training views, %d RGB frames, %d segment(s), %d steps each",
             info, train.n_views, len(train.frame_times), len(segments), cfg.trainer.max_steps)
    modules, wall = {}, 0.0
    for k in todo:
        modules[k], w = train_segment(cfg, ds, train, heldout, k, segments[k], out_dir, wall)
        wall += w
    steps = sum(int(m.global_step) for m in modules.values())
    merge_curves([out_dir / f"seg{k}" for k in todo], out_dir / "curve.csv")
    metrics: dict[str, Any] = {**info, "status": "ok", "error": None, "wall_s": wall,
                               "steps": steps, "sec_per_it": wall / max(steps, 1),
                               "nonfinite_steps": sum(m.nonfinite_total for m in modules.values()),
                               "segments": [[s.start, s.end] for s in segments]}
    if cfg.evaluate and heldout is not None and len(modules) == len(segments):
        fields = [modules[k].field.eval() for k in range(len(segments))]
        renderer = modules[0].renderer
        views = list(range(heldout.n_views)) if cfg.data.eval_views is None else list(cfg.data.eval_views)
        frames = list(range(0, len(heldout.frame_times), int(cfg.data.eval_every_frames)))
        renders = render_heldout(fields, segments, renderer, heldout, views, frames,
                                 chunk=cfg.trainer.chunk)
        write_renders(renders, heldout, views, frames, out_dir)
        metrics.update(evaluate_heldout(renders, heldout, views, frames))
    metrics["peak_mem_mb"] = _peak_mem_mb()
    metrics["total_s"] = time.perf_counter() - t_start
    atomic_write_json(out_dir / "metrics.json", metrics)
    return metrics


def evaluate_run(run_dir: Path, ckpt: str = "best", color_correct: bool = False) -> dict:
    """Re-evaluate a finished or interrupted run from its config and checkpoints."""
    from eventrecon.evaluate import evaluate_heldout, render_heldout, write_renders

    cfg_path = run_dir / ".hydra" / "config.yaml"
    if not cfg_path.exists():
        raise InputError(cfg_path, "<file>", "the run's saved Hydra config")
    cfg = OmegaConf.load(cfg_path)
    ds = load_dataset(cfg)
    heldout = ds.splits.get("validation")
    if heldout is None:
        raise InputError(ds.root, "validation/", "a held-out split to evaluate")
    segments = resolve_segments(ds.meta.get("segments"), cfg.loss.multiseg)
    renderer = build_renderer(cfg, ds.meta)
    fields = []
    for k in range(len(segments)):
        d = run_dir / f"seg{k}" / "checkpoints"
        path = d / f"{ckpt}.ckpt"
        if not path.exists():
            path = d / "last.ckpt"
        if not path.exists():
            raise InputError(d, f"{ckpt}.ckpt", "a checkpoint of every segment", "missing")
        state = torch.load(path, map_location="cpu", weights_only=False)
        field = build_field(cfg.model)
        sd = state["state_dict"]
        prepare = getattr(field, "prepare_state_dict", None)
        if prepare is not None:
            prepare(sd, prefix="field.")
        field.load_state_dict({k[6:]: v for k, v in sd.items() if k.startswith("field.")})
        renderer.clip_scale = state.get("eventrecon", {}).get("clip_scale", 1.0)
        fields.append(field.eval())
    views = list(range(heldout.n_views))
    frames = list(range(len(heldout.frame_times)))
    renders = render_heldout(fields, segments, renderer, heldout, views, frames)
    write_renders(renders, heldout, views, frames, run_dir)
    metrics = {**run_info(cfg, ds.meta), "checkpoint": ckpt,
               **evaluate_heldout(renders, heldout, views, frames, color_correct=color_correct)}
    name = "metrics_eval.json" if not color_correct else "metrics_eval_cc.json"
    atomic_write_json(run_dir / name, metrics)
    return metrics
