"""A run folder read back: its config, device and checkpoints, evaluated on the held-out views.

:func:`evaluate_run` is ``python -m eventrecon.evaluate run=DIR``: it loads a finished or
interrupted run (its ``.hydra/config.yaml`` and per-segment checkpoints) and scores it
(:mod:`eventrecon.evaluation.heldout`).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from eventrecon.common.errors import InputError
from eventrecon.common.files import atomic_write_json
from eventrecon.config.precision import image_dtype, run_precision
from eventrecon.data.batcher import Segment
from eventrecon.data.properties import SceneProperties
from eventrecon.data.selection import heldout_split, window_frames
from eventrecon.data.types import SplitData
from eventrecon.engine.build import load_dataset, load_segment, scene_properties
from eventrecon.engine.segments import run_segments, run_window
from eventrecon.evaluation.heldout import render_and_score
from eventrecon.evaluation.metrics import correction_mode
from eventrecon.fields.base import Field
from eventrecon.render.renderer import Renderer
from eventrecon.results.records import METRICS_FILE, read_metrics, run_info

__all__ = ["run_device", "evaluate_models", "run_config", "evaluate_run"]

log = logging.getLogger(__name__)


def run_device(cfg: DictConfig) -> torch.device:
    """Where the run trains and evaluates: its GPU when the trainer asks for one."""
    gpu = str(cfg.trainer.lightning.accelerator) in ("gpu", "cuda", "auto")
    return torch.device("cuda" if gpu and torch.cuda.is_available() else "cpu")


def evaluate_models(cfg: DictConfig, props: SceneProperties, heldout: SplitData,
                    segments: list[Segment], trained: dict[int, tuple[Field, Renderer]],
                    out_dir: Path, device: torch.device,
                    window: tuple[float, float] | None = None) -> dict[str, Any]:
    """Score a run's held-out views on ``device`` as configured (``data.eval_views``,
    ``data.eval_every_frames``; only the frames inside ``window`` when given); segments
    not in ``trained`` are loaded from their ``last.ckpt``."""
    models = []
    for k in range(len(segments)):
        field, renderer = (trained[k] if k in trained
                           else load_segment(cfg, props, out_dir / f"seg{k}"))
        models.append((field.to(device).eval(), renderer))
    views = (list(range(heldout.n_views)) if cfg.data.eval_views is None
             else list(cfg.data.eval_views))
    frames = window_frames(heldout, window, int(cfg.data.eval_every_frames))
    return render_and_score(models, segments, heldout, views, frames, out_dir,
                            cfg.render.chunk)


def _trained_precision(run_dir: Path, cfg: DictConfig) -> str | int:
    """The precision the run trained with: its record's, else the config's resolved here
    (an interrupted run has no record yet). Images render under it, not under what
    ``auto`` would pick on the machine that evaluates."""
    path = run_dir / METRICS_FILE
    try:
        return (read_metrics(path).get("precision") if path.exists() else None) or \
            run_precision(cfg)
    except InputError:
        return run_precision(cfg)


def run_config(run_dir: str | Path) -> DictConfig:
    """A run folder's saved config (``run_dir/.hydra/config.yaml``), or one
    :class:`InputError` naming the file when the folder holds none."""
    cfg_path = Path(run_dir) / ".hydra" / "config.yaml"
    if not cfg_path.is_file():
        raise InputError(cfg_path, "<file>", "the run's saved Hydra config")
    return OmegaConf.load(cfg_path)


def evaluate_run(run_dir: Path, ckpt: str = "last", color_correct: bool | str = "none") -> dict:
    """Re-evaluate a finished or interrupted run from its saved config and checkpoints.

    Every held-out view at every ground-truth time (the paper's protocol; the run's own
    ``metrics.json`` may have used a subset, ``data.eval_every_frames``).
    ``ckpt="last"`` (default) scores the final weights; ``"best"`` the checkpoint that
    scored best on the held-out views during training (a choice made on the test data
    itself, so not an unbiased score). Renders go to ``eval_<ckpt>/renders/``; the
    metrics to ``metrics_eval.json``
    beside the run's ``metrics.json``; with a colour correction (``per_image`` or
    ``eventnerf``, :data:`~eventrecon.evaluation.metrics.CORRECTIONS`) to
    ``metrics_eval_<correction>.json``.
    """
    run_dir = Path(run_dir)
    cfg = run_config(run_dir)
    ds = load_dataset(cfg)
    props = scene_properties(cfg, ds)
    heldout = heldout_split(ds)
    if heldout is None:
        raise InputError(ds.root, "validation/ or groundtruth/", "a held-out split to evaluate")
    window = run_window(cfg)
    segments = run_segments(cfg, props.segments)
    device = run_device(cfg)
    trained = _trained_precision(run_dir, cfg)
    models = [(field.to(device), renderer) for field, renderer in
              (load_segment(cfg, props, run_dir / f"seg{k}", ckpt, trained)
               for k in range(len(segments)))]
    views = list(range(heldout.n_views))
    frames = window_frames(heldout, window)
    metrics = {**run_info(cfg, ds.meta, data_id=Path(ds.root).name), "checkpoint": ckpt,
               "precision": str(trained),
               "image_autocast": image_dtype(cfg.render, trained, device.type) is not None,
               **render_and_score(models, segments, heldout, views, frames,
                                  run_dir / f"eval_{ckpt}", cfg.render.chunk, color_correct)}
    mode = correction_mode(color_correct)
    name = "metrics_eval.json" if mode == "none" else f"metrics_eval_{mode}.json"
    atomic_write_json(run_dir / name, metrics)
    return metrics
