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
import math
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf

from eventrecon.checkpointing import AtomicCheckpointIO, atomic_write_json, remove_stale_temporaries
from eventrecon.data.batcher import RayBatcher, Segment
from eventrecon.data.datamodule import SegmentDataModule
from eventrecon.data.properties import SceneProperties, resolve_properties
from eventrecon.data.types import Dataset, SplitData
from eventrecon.errors import InputError
from eventrecon.fields.base import Field
from eventrecon.losses import LossConfig
from eventrecon.memory import peak_mb, reset_peak
from eventrecon.module import EventNeRFModule, StepConfig, field_class_name
from eventrecon.render.volume import Renderer
from eventrecon.segments import resolve_segments

__all__ = ["run", "load_dataset", "segment_steps", "scene_properties", "build_field",
           "build_renderer", "build_module", "loss_config", "event_decay",
           "heldout_split", "check_training_split", "select_views", "select_fps",
           "train_segment", "load_segment", "evaluate_run", "run_info", "planned_run_info",
           "check_checkpoint"]

log = logging.getLogger(__name__)

#: The "w/o clipping" ablation: the cylinder covers the unit sphere's box.
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


def scene_properties(cfg: DictConfig, ds: Dataset) -> SceneProperties:
    """ε, θ, decay, Bayer, duration, segments and cylinder of the run's data
    (``data.*`` over ``meta.json``; see :mod:`eventrecon.data.properties`)."""
    return resolve_properties(cfg.data, ds.meta, ds.root)


def heldout_split(ds: Dataset) -> SplitData | None:
    """The split evaluated: ``groundtruth/`` (the published synthetic scenes' sharp
    held-out renders) when present, else ``validation/`` (ours: sharp renders too)."""
    return ds.splits.get("groundtruth") or ds.splits.get("validation")


def check_training_split(split: SplitData) -> None:
    """The training split has what the method needs: events and at least one RGB frame.

    Both folders are optional for the reader (a validation split has no events), so the
    requirement is checked here, before anything is trained, as one line naming the folder.
    """
    if split.events is None:
        raise InputError(Path(split.root) / "events", "<folder>",
                         "one events/<view>.npz per training view (the method learns from "
                         "events)", "missing")
    if len(split.frame_times) == 0:
        raise InputError(Path(split.root) / "rgb", "<folder>",
                         "at least one rgb/<frame>/<view>.png (L_acc and L_rgb need a "
                         "reference frame)", "missing")


def select_views(split: SplitData, n: int | None) -> SplitData:
    """An evenly spread subset of ``n`` views of the ring (all when ``n`` is None)."""
    V = split.n_views
    if n is None or n == V:
        return split
    if not 1 <= n <= V:
        raise InputError("config", "data.views", f"an integer in [1, {V}] (views in the dataset)",
                         n)
    idx = sorted({int(i) for i in np.floor(np.arange(n) * V / n)})
    return replace(
        split, cameras=split.cameras.select(idx),
        events=None if split.events is None else [split.events[i] for i in idx],
        frames=split.frames[:, idx],
        background=None if split.background is None else split.background[idx],
        masks=None if split.masks is None else split.masks[:, idx])


def select_fps(split: SplitData, fps: float | None, duration_s: float) -> SplitData:
    """The frames nearest to the grid ``k · 1000 / (fps · duration_s)``, ``k < fps · duration_s``.

    A rate ``F`` over a clip of ``D`` seconds keeps ``max(1, floor(F·D))`` frames (the grid
    is half-open, like a camera's shutter): 0.5 FPS over 2 s is one set of frames, as in
    the supplementary's 0.5 FPS row of Tab. 5. The dataset's own rate keeps every frame.
    """
    if fps is None:
        return split
    if fps <= 0:
        raise InputError("config", "data.fps", "a positive frame rate", fps)
    times = np.asarray(split.frame_times, dtype=np.float64)
    step = 1000.0 / (fps * duration_s)
    native_step = float(np.min(np.diff(times))) if len(times) > 1 else math.inf
    if step < native_step - 1e-6:
        native = 1000.0 / (native_step * duration_s)
        raise InputError("config", "data.fps", f"at most the dataset's {native:g} FPS", fps)
    if step <= native_step + 1e-6:
        return split
    n = max(1, int(math.floor(fps * duration_s + 1e-9)))
    grid = np.arange(n) * step
    keep = sorted({int(np.argmin(np.abs(times - g))) for g in grid})
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


def build_renderer(cfg: DictConfig, props: SceneProperties) -> Renderer:
    """The renderer with the run's samples and clipping cylinder (``loss.clipping``)."""
    cyl = dict(props.cylinder) if cfg.loss.clipping else dict(NO_CLIPPING)
    return Renderer(n_coarse=cfg.trainer.n_coarse, n_fine=cfg.trainer.n_fine,
                    chunk=cfg.trainer.chunk, **cyl)


def loss_config(cfg: DictConfig, props: SceneProperties) -> LossConfig:
    """The loss weights of ``cfg.loss`` with the data's ε and θ."""
    lc = cfg.loss
    return LossConfig(w_event=lc.w_event, w_acc=lc.w_acc, w_rgb=lc.w_rgb,
                      lam_sparsity=lc.lam_sparsity, sparsity_ramp=lc.sparsity_ramp,
                      eps=props.tonemap_eps, theta=props.threshold)


def event_decay(cfg: DictConfig, props: SceneProperties) -> float:
    """``b``: ``loss.decay`` (the "w/o decay" ablation sets 1) over the data's own."""
    return float(cfg.loss.decay) if cfg.loss.decay is not None else props.decay


def build_module(cfg: DictConfig, props: SceneProperties, train: SplitData | None,
                 seg: Segment, k: int = 0, device: str | torch.device = "cpu"
                 ) -> EventNeRFModule:
    """The LightningModule of segment ``k``: field, renderer, losses, step settings.

    With ``train`` the module gets its own :class:`RayBatcher` on ``device`` (tests,
    notebooks); with ``None`` it takes the batcher of the trainer's
    :class:`~eventrecon.data.datamodule.SegmentDataModule` (training runs).
    """
    field = build_field(cfg.model)
    batcher = None
    if train is not None:
        batcher = RayBatcher(train, seg, decay=event_decay(cfg, props), bayer=props.bayer,
                             neg_ratio=cfg.data.neg_ratio, device=device)
    optim = cfg.model.get("optim", {}) or {}
    lr = cfg.trainer.lr if cfg.trainer.lr is not None else optim.get("lr", 1e-3)
    step = StepConfig(n_rays=cfg.trainer.n_rays, lr=float(lr),
                      weight_decay=float(optim.get("weight_decay", 0.0)),
                      max_nonfinite=cfg.trainer.max_nonfinite, log_every=cfg.trainer.log_every,
                      seed=cfg.seed + 1000 * k)
    return EventNeRFModule(field, build_renderer(cfg, props), batcher,
                           loss_config(cfg, props), step)


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


def segment_steps(cfg: DictConfig, n_segments: int) -> int:
    """Optimiser steps of each segment: ``trainer.max_steps`` (the paper: every segment
    trains as long as a one-segment run), or with ``trainer.split_steps=true`` the run's
    budget ``ceil(max_steps / n_segments)`` (equal compute for any number of segments,
    the CPU sweeps' choice).

    >>> segment_steps(OmegaConf.create({"trainer": {"max_steps": 1000, "split_steps": True}}), 3)
    334
    """
    total = int(cfg.trainer.max_steps)
    return math.ceil(total / n_segments) if cfg.trainer.get("split_steps") else total


def _trainer(cfg: DictConfig, seg_dir: Path, callbacks: list, k: int,
             max_steps: int) -> L.Trainer:
    from lightning.pytorch.callbacks import ModelCheckpoint

    ckpt = ModelCheckpoint(dirpath=seg_dir / "checkpoints", save_last=True, save_top_k=0,
                           every_n_train_steps=cfg.trainer.checkpoint_every)
    logger: Any = False
    if cfg.logger and cfg.logger.get("_target_"):
        lg = dict(OmegaConf.to_container(cfg.logger, resolve=True))
        logger = get_class(lg.pop("_target_"))(save_dir=str(seg_dir.parent), version=f"seg{k}",
                                               **lg)
        logger.log_hyperparams(flat_hparams(cfg))
    kwargs = OmegaConf.to_container(cfg.trainer.lightning, resolve=True)
    return L.Trainer(max_steps=max_steps, default_root_dir=str(seg_dir),
                     logger=logger, callbacks=[ckpt, *callbacks],
                     plugins=[AtomicCheckpointIO()], log_every_n_steps=cfg.trainer.log_every,
                     enable_model_summary=False, **kwargs)


def train_segment(cfg: DictConfig, props: SceneProperties, train: SplitData,
                  heldout: SplitData | None, k: int, seg: Segment, out_dir: Path,
                  wall_offset: float = 0.0, max_steps: int | None = None
                  ) -> tuple[EventNeRFModule, float]:
    """Train (or resume) segment ``k`` for ``max_steps`` (default ``trainer.max_steps``);
    returns the module and its training seconds."""
    max_steps = int(cfg.trainer.max_steps) if max_steps is None else int(max_steps)
    from eventrecon.callbacks import HeldOutMonitor

    seg_dir = out_dir / f"seg{k}"
    L.seed_everything(cfg.seed + 1000 * k, workers=True, verbose=False)
    module = build_module(cfg, props, None, seg, k)
    data = SegmentDataModule(train, seg, event_decay(cfg, props), props.bayer,
                             cfg.data.neg_ratio)
    callbacks = list(module.field.callbacks())
    monitor = None
    if heldout is not None:
        monitor = HeldOutMonitor(heldout, seg, seg_dir, cfg.trainer.curve_every,
                                 cfg.trainer.eval_every, cfg.trainer.image_every,
                                 cfg.trainer.curve_pixels, cfg.trainer.chunk, cfg.seed,
                                 wall_offset)
        callbacks.append(monitor)
    trainer = _trainer(cfg, seg_dir, callbacks, k, max_steps)
    ckpt = None
    removed = remove_stale_temporaries(seg_dir / "checkpoints")
    if removed:
        log.info("segment %d: removed %d temporary file(s) of an interrupted checkpoint write",
                 k, len(removed))
    if cfg.ckpt_path == "last":
        last = seg_dir / "checkpoints" / "last.ckpt"
        ckpt = str(last) if last.exists() else None
    elif cfg.ckpt_path:
        ckpt = str(cfg.ckpt_path)
    if ckpt:
        check_checkpoint(ckpt, module.field)
        log.info("segment %d: resuming from %s", k, ckpt)
    t = time.perf_counter()
    trainer.fit(module, datamodule=data, ckpt_path=ckpt)
    last = seg_dir / "checkpoints" / "last.ckpt"
    if module.stop_reason is None and _checkpoint_step(last) != int(trainer.global_step):
        trainer.save_checkpoint(str(last), weights_only=False)  # the final step's weights
    wall = monitor.wall - wall_offset if monitor is not None else time.perf_counter() - t
    return module, wall


def _checkpoint_step(path: Path) -> int | None:
    """``global_step`` stored in a checkpoint (``None`` if there is none)."""
    if not path.exists():
        return None
    return int(torch.load(path, map_location="cpu", weights_only=False, mmap=True)
               .get("global_step", -1))


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


def _global_rank() -> int:
    """This process's rank in a multi-GPU (DDP) run; 0 otherwise."""
    from lightning.pytorch.utilities.rank_zero import rank_zero_only

    return int(getattr(rank_zero_only, "rank", 0) or 0)


def _done(seg_dir: Path, max_steps: int) -> dict | None:
    """The ``done.json`` of a segment trained to at least ``max_steps``, else ``None``."""
    path = seg_dir / "done.json"
    if not path.exists():
        return None
    done = json.loads(path.read_text())
    return done if int(done.get("max_steps", -1)) >= max_steps else None


def load_segment(cfg: DictConfig, props: SceneProperties, seg_dir: Path, ckpt: str = "last"
                 ) -> tuple[Field, Renderer]:
    """Field and renderer of a trained segment from ``seg_dir/checkpoints/<ckpt>.ckpt``.

    The renderer carries the segment's own ``clip_scale`` (cylinder annealing state).
    """
    d = seg_dir / "checkpoints"
    path = d / f"{ckpt}.ckpt"
    if not path.exists():
        raise InputError(d, f"{ckpt}.ckpt", "a checkpoint of every segment", "missing")
    field = build_field(cfg.model)
    check_checkpoint(path, field)
    state = torch.load(path, map_location="cpu", weights_only=False)
    sd = state["state_dict"]
    prepare = getattr(field, "prepare_state_dict", None)
    if prepare is not None:  # backbones whose tensors grow during training
        prepare(sd, prefix="field.")
    field.load_state_dict({k[6:]: v for k, v in sd.items() if k.startswith("field.")})
    renderer = build_renderer(cfg, props)
    renderer.clip_scale = float(state.get("eventrecon", {}).get("clip_scale", 1.0))
    return field.eval(), renderer


def run(cfg: DictConfig, out_dir: str | Path) -> dict[str, Any]:
    """Train every segment of the run and evaluate; returns (and saves) the metrics.

    Segments already trained to ``max_steps`` (their ``seg<k>/done.json``) are not
    trained again. With ``data.segment=k`` only segment ``k`` is trained; the job that
    completes the last missing segment of the folder evaluates the whole run (so a
    multirun over ``data.segment``, whose jobs share one folder, ends cross-faded).
    """
    from eventrecon.evaluate import evaluate_heldout, render_heldout, write_renders

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    reset_peak()
    ds = load_dataset(cfg)
    if "train" not in ds.splits:
        raise InputError(ds.root, "train/", "a training split")
    props = scene_properties(cfg, ds)
    check_training_split(ds.splits["train"])
    train = select_views(ds.splits["train"], cfg.data.views)
    train = select_fps(train, cfg.data.fps, props.duration_s)
    heldout = heldout_split(ds)
    segments = resolve_segments(props.segments, cfg.loss.multiseg)
    if cfg.data.segment is not None and not 0 <= int(cfg.data.segment) < len(segments):
        raise InputError("config", "data.segment",
                         f"a segment index in [0, {len(segments) - 1}]", cfg.data.segment)
    todo = range(len(segments)) if cfg.data.segment is None else [int(cfg.data.segment)]
    info = run_info(cfg, ds.meta, views=train.n_views, fps=cfg.data.fps or props.rgb_fps)
    max_steps = segment_steps(cfg, len(segments))
    log.info("run %s: %d training views, %d RGB frames, %d segment(s), %d steps each",
             info, train.n_views, len(train.frame_times), len(segments), max_steps)
    modules: dict[int, EventNeRFModule] = {}
    wall = 0.0
    for k in todo:
        seg_dir = out_dir / f"seg{k}"
        if _done(seg_dir, max_steps) is not None:
            log.info("segment %d: trained before (%s), not trained again", k,
                     seg_dir / "done.json")
            continue
        modules[k], w = train_segment(cfg, props, train, heldout, k, segments[k], out_dir, wall,
                                      max_steps)
        wall += w
        if _global_rank() != 0:
            continue  # DDP: rank 0 records and evaluates
        atomic_write_json(seg_dir / "done.json", {
            "max_steps": max_steps, "steps": int(modules[k].global_step), "wall_s": w,
            "nonfinite_steps": modules[k].nonfinite_total})
    if _global_rank() != 0:
        return {**info, "status": "ok", "error": None, "rank": _global_rank()}
    dones = [_done(out_dir / f"seg{k}", max_steps) for k in range(len(segments))]
    metrics: dict[str, Any] = {**info, "status": "ok", "error": None,
                               "max_steps": int(cfg.trainer.max_steps),
                               "steps_per_segment": max_steps,
                               "segments": [[s.start, s.end] for s in segments]}
    if any(d is None for d in dones):
        missing = [k for k, d in enumerate(dones) if d is None]
        log.info("segments %s not trained yet: the run is evaluated when they are", missing)
        return {**metrics, "status": "partial", "missing_segments": missing}
    steps = sum(int(d["steps"]) for d in dones)
    wall_all = sum(float(d["wall_s"]) for d in dones)
    metrics.update({"wall_s": wall_all, "steps": steps, "sec_per_it": wall_all / max(steps, 1),
                    "nonfinite_steps": sum(int(d["nonfinite_steps"]) for d in dones)})
    merge_curves([out_dir / f"seg{k}" for k in range(len(segments))], out_dir / "curve.csv")
    if cfg.evaluate and heldout is not None:
        models = [(modules[k].field.eval(), modules[k].renderer) if k in modules
                  else load_segment(cfg, props, out_dir / f"seg{k}")
                  for k in range(len(segments))]
        views = (list(range(heldout.n_views)) if cfg.data.eval_views is None
                 else list(cfg.data.eval_views))
        frames = list(range(0, len(heldout.frame_times), int(cfg.data.eval_every_frames)))
        renders = render_heldout(models, segments, heldout, views, frames,
                                 chunk=cfg.trainer.chunk)
        write_renders(renders, heldout, views, frames, out_dir)
        metrics.update(evaluate_heldout(renders, heldout, views, frames))
    metrics["peak_mem_mb"] = peak_mb()
    metrics["total_s"] = time.perf_counter() - t_start
    atomic_write_json(out_dir / "metrics.json", metrics)
    return metrics


def evaluate_run(run_dir: Path, ckpt: str = "last", color_correct: bool = False) -> dict:
    """Re-evaluate a finished or interrupted run from its saved config and checkpoints.

    ``ckpt="last"`` (default) scores the final weights; ``"best"`` the checkpoint that
    scored best on the held-out views during training (a choice made on the test data
    itself, so not an unbiased score). Writes ``metrics_eval.json`` (or
    ``metrics_eval_cc.json`` with colour correction) beside the run's ``metrics.json``.
    """
    from eventrecon.evaluate import evaluate_heldout, render_heldout, write_renders

    run_dir = Path(run_dir)
    cfg_path = run_dir / ".hydra" / "config.yaml"
    if not cfg_path.exists():
        raise InputError(cfg_path, "<file>", "the run's saved Hydra config")
    cfg = OmegaConf.load(cfg_path)
    ds = load_dataset(cfg)
    props = scene_properties(cfg, ds)
    heldout = heldout_split(ds)
    if heldout is None:
        raise InputError(ds.root, "validation/ or groundtruth/", "a held-out split to evaluate")
    segments = resolve_segments(props.segments, cfg.loss.multiseg)
    models = [load_segment(cfg, props, run_dir / f"seg{k}", ckpt) for k in range(len(segments))]
    views = list(range(heldout.n_views))
    frames = list(range(len(heldout.frame_times)))
    renders = render_heldout(models, segments, heldout, views, frames, chunk=cfg.trainer.chunk)
    write_renders(renders, heldout, views, frames, run_dir)
    metrics = {**run_info(cfg, ds.meta), "checkpoint": ckpt,
               **evaluate_heldout(renders, heldout, views, frames, color_correct=color_correct)}
    name = "metrics_eval.json" if not color_correct else "metrics_eval_cc.json"
    atomic_write_json(run_dir / name, metrics)
    return metrics
