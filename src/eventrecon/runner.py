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
from eventrecon.locks import exclusive
from eventrecon.losses import LossConfig
from eventrecon.memory import peak_mb, reset_peak
from eventrecon.module import EventNeRFModule, StepConfig, field_class_name
from eventrecon.render.volume import Renderer
from eventrecon.segments import resolve_segments

__all__ = ["run", "load_dataset", "segment_steps", "scene_properties", "build_field",
           "build_renderer", "build_module", "loss_config", "event_decay",
           "heldout_split", "check_training_split", "select_views", "select_fps",
           "train_segment", "load_segment", "evaluate_run", "run_info", "planned_run_info",
           "check_checkpoint", "finished_metrics"]

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
    if len(times) < 2:
        return split  # one set of frames: every rate keeps it
    step = 1000.0 / (fps * duration_s)
    native_step = float(np.median(np.diff(times)))
    tol = 1e-3 * native_step  # frame folders are named to 1e-4 time units
    if step < native_step - tol:
        native = 1000.0 / (native_step * duration_s)
        raise InputError("config", "data.fps", f"at most the dataset's {native:g} FPS", fps)
    if step <= native_step + tol:
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
    """One ``curve.csv`` for the run: the segments' rows in order, with step and wall-clock
    made cumulative (each segment starts where the previous one's ``done.json`` ended)."""
    import csv

    rows: list[dict[str, str]] = []
    step0, wall0 = 0, 0.0
    for d in seg_dirs:
        path = d / "curve.csv"
        if path.exists():
            with path.open(newline="") as f:
                for r in csv.DictReader(f):
                    r["step"] = str(int(r["step"]) + step0)
                    r["wall_s"] = f"{float(r['wall_s']) + wall0:.3f}"
                    rows.append(r)
        done = json.loads((d / "done.json").read_text()) if (d / "done.json").exists() else {}
        step0 += int(done.get("steps", 0))
        wall0 += float(done.get("wall_s", 0.0))
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


def segment_config(cfg: DictConfig, steps: int) -> DictConfig:
    """``cfg`` with ``trainer.max_steps`` = the segment's own steps, so that schedules written
    as fractions of the run (``${of_run:f}``) take the shape of the run each model trains."""
    if int(cfg.trainer.max_steps) == steps and not cfg.trainer.get("split_steps"):
        return cfg
    return OmegaConf.merge(cfg, {"trainer": {"max_steps": steps, "split_steps": False}})


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
                  heldout: SplitData | None, k: int, seg: Segment, out_dir: Path
                  ) -> tuple[EventNeRFModule, float]:
    """Train (or resume) segment ``k`` for ``cfg.trainer.max_steps`` steps (a config from
    :func:`segment_config`); returns the module and the segment's training seconds (a
    resumed segment counts the time before the interruption too)."""
    from eventrecon.callbacks import HeldOutMonitor

    max_steps = int(cfg.trainer.max_steps)
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
                                 cfg.trainer.curve_pixels, cfg.trainer.chunk, cfg.seed)
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
        step = _checkpoint_step(Path(ckpt))
        if step is not None and step > max_steps:
            raise InputError(ckpt, "global_step",
                             f"at most this run's {max_steps} steps per segment (a run "
                             "trained longer: use a new output folder)", step)
        log.info("segment %d: resuming from %s (step %s)", k, ckpt, step)
    t = time.perf_counter()
    trainer.fit(module, datamodule=data, ckpt_path=ckpt)
    if module.stop_reason is None:  # every rank: saving is a collective call under DDP
        trainer.save_checkpoint(str(seg_dir / "checkpoints" / "last.ckpt"), weights_only=False)
    wall = monitor.wall if monitor is not None else time.perf_counter() - t
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
    """The ``done.json`` of a segment trained with exactly this budget, else ``None``."""
    path = seg_dir / "done.json"
    if not path.exists():
        return None
    done = json.loads(path.read_text())
    return done if int(done.get("max_steps", -1)) == max_steps else None


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


def _device(cfg: DictConfig) -> torch.device:
    """Where the run trains (and evaluates): its GPU when the trainer asks for one."""
    gpu = str(cfg.trainer.lightning.accelerator) in ("gpu", "cuda", "auto")
    return torch.device("cuda" if gpu and torch.cuda.is_available() else "cpu")


def run(cfg: DictConfig, out_dir: str | Path) -> dict[str, Any]:
    """Train every segment of the run and evaluate; returns (and saves) the metrics.

    Each segment trains ``segment_steps`` steps with the config of :func:`segment_config`
    and records ``seg<k>/done.json``; a segment done with this budget is not trained again.
    With ``data.segment=k`` only segment ``k`` is trained; the job that completes the last
    missing segment of the folder evaluates the whole run, under a lock, once (a multirun
    over ``data.segment``, whose jobs share one folder, ends cross-faded).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    device = _device(cfg)
    reset_peak(cuda=device.type == "cuda")
    ds = load_dataset(cfg)
    if "train" not in ds.splits:
        raise InputError(ds.root, "train/", "a training split")
    props = scene_properties(cfg, ds)
    check_training_split(ds.splits["train"])
    train = select_views(ds.splits["train"], cfg.data.views)
    if cfg.data.fps is not None and props.duration_s is None:
        raise InputError("config", "data.duration_s", "the clip's length in seconds (data.fps "
                         "needs it; the dataset's meta.json does not say)", "missing")
    train = select_fps(train, cfg.data.fps, props.duration_s or 1.0)
    heldout = heldout_split(ds)
    segments = resolve_segments(props.segments, cfg.loss.multiseg)
    if cfg.data.segment is not None and not 0 <= int(cfg.data.segment) < len(segments):
        raise InputError("config", "data.segment",
                         f"a segment index in [0, {len(segments) - 1}]", cfg.data.segment)
    todo = range(len(segments)) if cfg.data.segment is None else [int(cfg.data.segment)]
    if cfg.ckpt_path not in (None, "last") and len(todo) > 1:
        raise InputError("config", "ckpt_path", f"'last', or one checkpoint with data.segment=K "
                         f"(one file cannot resume {len(todo)} segments)", cfg.ckpt_path)
    info = run_info(cfg, ds.meta, views=train.n_views, fps=cfg.data.fps or props.rgb_fps)
    steps = segment_steps(cfg, len(segments))
    seg_cfg = segment_config(cfg, steps)
    log.info("run %s: %d training views, %d RGB frames, %d segment(s), %d steps each",
             info, train.n_views, len(train.frame_times), len(segments), steps)
    modules: dict[int, EventNeRFModule] = {}
    for k in todo:
        seg_dir = out_dir / f"seg{k}"
        if _done(seg_dir, steps) is not None:
            log.info("segment %d: trained before (%s), not trained again", k,
                     seg_dir / "done.json")
            continue
        module, wall = train_segment(seg_cfg, props, train, heldout, k, segments[k], out_dir)
        if _global_rank() != 0:
            continue  # DDP: rank 0 records and evaluates
        atomic_write_json(seg_dir / "done.json", {
            "max_steps": steps, "steps": int(module.global_step), "wall_s": wall,
            "nonfinite_steps": module.nonfinite_total})
        module.batcher = None  # the segment's training data is not needed any more
        modules[k] = module
    if _global_rank() != 0:
        return {**info, "status": "ok", "error": None, "rank": _global_rank()}
    metrics: dict[str, Any] = {**info, "status": "ok", "error": None,
                               "max_steps": int(cfg.trainer.max_steps),
                               "steps_per_segment": steps,
                               "segments": [[s.start, s.end] for s in segments]}
    dones = [_done(out_dir / f"seg{k}", steps) for k in range(len(segments))]
    if any(d is None for d in dones):
        missing = [k for k, d in enumerate(dones) if d is None]
        log.info("segments %s not trained yet: the run is evaluated when they are", missing)
        return {**metrics, "status": "partial", "missing_segments": missing}
    metrics.update({"steps": sum(int(d["steps"]) for d in dones),
                    "wall_s": sum(float(d["wall_s"]) for d in dones),
                    "nonfinite_steps": sum(int(d["nonfinite_steps"]) for d in dones)})
    metrics["sec_per_it"] = metrics["wall_s"] / max(metrics["steps"], 1)
    with exclusive(out_dir / ".evaluate.lock"):  # parallel segment jobs: evaluate once
        previous = finished_metrics(out_dir / "metrics.json", metrics["max_steps"],
                                    cfg.evaluate, metrics["steps"])
        if previous is not None:
            return previous
        merge_curves([out_dir / f"seg{k}" for k in range(len(segments))],
                     out_dir / "curve.csv")
        if cfg.evaluate and heldout is not None:
            metrics.update(_evaluate(seg_cfg, props, heldout, segments, modules, out_dir,
                                     device))
        metrics["peak_mem_mb"] = peak_mb(cuda=device.type == "cuda")
        metrics["total_s"] = time.perf_counter() - t_start
        atomic_write_json(out_dir / "metrics.json", metrics)
    return metrics


def finished_metrics(path: Path, max_steps: int, evaluate: bool,
                     steps: int | None = None) -> dict | None:
    """``metrics.json`` of the same finished run (status ok, the same ``max_steps`` and,
    when given, the same ``steps``; scored if ``evaluate``), else ``None``."""
    if not path.exists():
        return None
    done = json.loads(path.read_text())
    same = (done.get("status") == "ok" and done.get("max_steps") == int(max_steps)
            and (steps is None or done.get("steps") == steps))
    return done if same and (not evaluate or "psnr" in done) else None


def _render_and_score(models: list[tuple[Field, Renderer]], segments: list[Segment],
                      heldout: SplitData, views: list[int], frames: list[int], out_dir: Path,
                      chunk: int, color_correct: bool = False) -> dict[str, Any]:
    """Render the held-out ``views`` at ``frames`` (cross-fading segments), write the PNGs
    and GIFs below ``out_dir`` and return PSNR / SSIM / LPIPS (and ``psnr_background``)."""
    from eventrecon.evaluate import evaluate_heldout, render_heldout, write_renders

    renders = render_heldout(models, segments, heldout, views, frames, chunk=chunk)
    write_renders(renders, heldout, views, frames, out_dir)
    return evaluate_heldout(renders, heldout, views, frames, color_correct=color_correct)


def _evaluate(cfg: DictConfig, props: SceneProperties, heldout: SplitData,
              segments: list[Segment], modules: dict[int, EventNeRFModule], out_dir: Path,
              device: torch.device) -> dict[str, Any]:
    """Score the run's held-out views on ``device`` as configured (``data.eval_views``,
    ``data.eval_every_frames``). Segments not trained by this process are loaded."""
    models = []
    for k in range(len(segments)):
        field, renderer = ((modules[k].field, modules[k].renderer) if k in modules
                           else load_segment(cfg, props, out_dir / f"seg{k}"))
        models.append((field.to(device).eval(), renderer))
    views = (list(range(heldout.n_views)) if cfg.data.eval_views is None
             else list(cfg.data.eval_views))
    frames = list(range(0, len(heldout.frame_times), int(cfg.data.eval_every_frames)))
    return _render_and_score(models, segments, heldout, views, frames, out_dir,
                             cfg.trainer.chunk)


def evaluate_run(run_dir: Path, ckpt: str = "last", color_correct: bool = False) -> dict:
    """Re-evaluate a finished or interrupted run from its saved config and checkpoints.

    Every held-out view at every ground-truth time (the paper's protocol; the run's own
    ``metrics.json`` may have used a subset, ``data.eval_every_frames``).
    ``ckpt="last"`` (default) scores the final weights; ``"best"`` the checkpoint that
    scored best on the held-out views during training (a choice made on the test data
    itself, so not an unbiased score). Renders go to ``eval_<ckpt>/renders/``; the
    metrics to ``metrics_eval.json`` (``metrics_eval_cc.json`` with colour correction)
    beside the run's ``metrics.json``.
    """
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
    device = _device(cfg)
    models = [(field.to(device), renderer) for field, renderer in
              (load_segment(cfg, props, run_dir / f"seg{k}", ckpt) for k in range(len(segments)))]
    views = list(range(heldout.n_views))
    frames = list(range(len(heldout.frame_times)))
    metrics = {**run_info(cfg, ds.meta), "checkpoint": ckpt,
               **_render_and_score(models, segments, heldout, views, frames,
                                   run_dir / f"eval_{ckpt}", cfg.trainer.chunk, color_correct)}
    name = "metrics_eval.json" if not color_correct else "metrics_eval_cc.json"
    atomic_write_json(run_dir / name, metrics)
    return metrics
