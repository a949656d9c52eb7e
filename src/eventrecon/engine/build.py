"""From config to objects: the dataset, the field, the renderer, the losses, the module.

Every object a run is made of is built here from its config group, through one checked
:func:`instantiate` (``_target_`` plus the node's keys as arguments), so a typo in a
class path or an argument is one line naming the config key, not a traceback:

- ``cfg.model``  → the :class:`~eventrecon.fields.base.Field` (``model.optim`` holds the
  optimiser settings, read by :func:`build_module`);
- ``cfg.render`` → the :class:`~eventrecon.render.renderer.Renderer` (the volume
  renderer by default), with the scene's clipping cylinder;
- ``cfg.loss``   → the :class:`~eventrecon.engine.losses.LossConfig`, with the scene's ε and θ;
- ``cfg.logger`` and ``cfg.trainer.callbacks`` → Lightning's logger and extra callbacks.

The dataset is read (``data.root``) or simulated (``scene``); its physical properties
come from :func:`eventrecon.data.properties.resolve_properties`. Checkpoints are
inspected here too (readable, of this run's backbone, how far trained), opening the
file once, memory-mapped.
"""

from __future__ import annotations

import importlib
import json
import logging
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import InterpolationResolutionError

from eventrecon.common.errors import InputError
from eventrecon.config.precision import image_dtype, run_precision
from eventrecon.data.batcher import RayBatcher, Segment
from eventrecon.data.properties import SceneProperties, resolve_properties
from eventrecon.data.types import Dataset, SplitData
from eventrecon.engine.losses import LossConfig
from eventrecon.engine.module import EventNeRFModule, StepConfig, field_class_name
from eventrecon.engine.optim import (
    adam_betas,
    lr_decay_start,
    lr_end_factor,
    lr_warmup,
    optim_numbers,
)
from eventrecon.fields.base import Field
from eventrecon.render.renderer import Renderer
from eventrecon.results.records import run_info

__all__ = ["instantiate", "load_dataset", "scene_properties", "build_field",
           "build_renderer", "build_loss", "build_module", "build_logger",
           "build_callbacks", "planned_run_info", "CheckpointInfo", "inspect_checkpoint",
           "load_segment"]

log = logging.getLogger(__name__)

#: Keys of a model or loss node that describe the object rather than construct it (the
#: row name in the reports, the optimiser settings, whether bf16 pays on a CPU:
#: :mod:`eventrecon.config.precision`).
DESCRIPTIVE_KEYS: tuple[str, ...] = ("name", "optim", "cpu_bf16")


def instantiate(node: DictConfig | dict, where: str, base: type | None = None,
                skip: tuple[str, ...] = (), **extra: Any) -> Any:
    """``node._target_(**node, **extra)``, checked (:func:`target_and_arguments`; an
    argument the class does not take is one :class:`InputError` naming ``where`` too).

    >>> instantiate({"_target_": "eventrecon.engine.losses.LossConfig", "name": "x", "w_rgb": 0.5},
    ...             "loss", skip=("name",)).w_rgb
    0.5
    >>> try:
    ...     instantiate({"_target_": "eventrecon.engine.losses.Nope"}, "loss")
    ... except InputError as e:
    ...     print(str(e)[:81])
    config: loss._target_: expected an importable class (a _target_ as in conf/loss/)
    """
    cls, kwargs = target_and_arguments(node, where, base, skip)
    target = f"{cls.__module__}.{cls.__qualname__}"
    try:
        return cls(**kwargs, **extra)
    except TypeError as e:  # an argument the class does not take (`+model.foo=1`)
        raise InputError("config", where, f"the arguments of {target}", str(e)) from None


def target_and_arguments(node: DictConfig | dict, where: str, base: type | None = None,
                         skip: tuple[str, ...] = ()) -> tuple[type, dict[str, Any]]:
    """The class ``node._target_`` names and the arguments ``node`` gives it (resolved;
    keys in ``skip`` left out), checked without building anything: a failure to resolve
    or import, a target that is not a ``base``, or a value whose type cannot be the
    ``int`` / ``float`` / ``bool`` its constructor declares (:func:`_check_scalar_types`)
    is one :class:`InputError` naming ``where`` (the config key).

    >>> target_and_arguments({"_target_": "eventrecon.engine.losses.LossConfig", "w_rgb": 1},
    ...                      "loss")
    (<class 'eventrecon.engine.losses.LossConfig'>, {'w_rgb': 1})
    """
    try:
        kwargs = (OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig)
                  else dict(node))
    except InterpolationResolutionError as e:  # a resolver's own one-line error
        if isinstance(e.__cause__, InputError):
            raise e.__cause__ from None
        raise InputError("config", where, "resolvable values", str(e).splitlines()[0]) from None
    assert isinstance(kwargs, dict)
    target = kwargs.pop("_target_", None)
    for key in skip:
        kwargs.pop(key, None)
    kind = f"{base.__name__} class" if base is not None else "class"
    expect = f"an importable {kind} (a _target_ as in conf/{where.split('.')[0]}/)"
    if not target:
        raise InputError("config", f"{where}._target_", expect, "nothing")
    module, _, name = str(target).rpartition(".")
    try:
        cls = getattr(importlib.import_module(module), name) if module else None
    except (ImportError, AttributeError) as e:
        raise InputError("config", f"{where}._target_", expect,
                         f"{target} ({type(e).__name__}: {e})") from None
    if not isinstance(cls, type) or (base is not None and not issubclass(cls, base)):
        raise InputError("config", f"{where}._target_", expect, target)
    _check_scalar_types(cls, kwargs, where)
    return cls, kwargs


#: What a config value of an ``int``, ``float`` or ``bool`` argument must be, by annotation.
_SCALARS: dict[Any, tuple[tuple[type, ...], str]] = {
    int: ((int,), "an integer"), float: ((int, float), "a number"),
    bool: ((bool,), "true or false")}


def _check_scalar_types(cls: type, kwargs: dict[str, Any], where: str) -> None:
    """One :class:`InputError` naming ``where.key`` for a value whose type cannot be the
    ``int``, ``float`` or ``bool`` (or ``None``, where allowed) that ``cls``'s constructor
    declares for it (a word where a number belongs would otherwise fail inside the
    constructor, as a comparison's ``TypeError`` or ``int()``'s ``ValueError``).
    Arguments with other annotations, or none, are left to the constructor."""
    try:
        hints = typing.get_type_hints(cls.__init__)
    except Exception:  # noqa: BLE001 - unresolvable annotations: nothing to check against
        return
    for key, value in kwargs.items():
        hint = hints.get(key)
        args = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union,
                                                                   types.UnionType) else ()
        optional = type(None) in args
        scalar = [a for a in args if a is not type(None)] if args else [hint]
        if len(scalar) != 1 or scalar[0] not in _SCALARS or (value is None and optional):
            continue
        allowed, words = _SCALARS[scalar[0]]
        if isinstance(value, bool) != (scalar[0] is bool) or not isinstance(value, allowed):
            raise InputError("config", f"{where}.{key}",
                             words + (" or null" if optional else ""), value)


# ---------------------------------------------------------------------------- data
def load_dataset(cfg: DictConfig) -> Dataset:
    """The dataset of a run: ``data.root`` if given, else the simulated ``scene``."""
    from eventrecon.data.layout import read_dataset

    if cfg.data.root:
        return read_dataset(Path(cfg.data.root))
    from eventrecon.sim.pipeline import ensure_dataset

    return read_dataset(ensure_dataset(cfg.scene, cfg.data_dir))


def scene_properties(cfg: DictConfig, ds: Dataset) -> SceneProperties:
    """ε, θ, decay, Bayer, duration, segments and cylinder of the run's data
    (``data.*`` over ``meta.json`` over ``data.fallback``)."""
    return resolve_properties(cfg.data, ds.meta, ds.root)


def planned_run_info(cfg: DictConfig) -> dict[str, Any]:
    """:func:`~eventrecon.results.records.run_info` of a run that may have failed before reading
    its data (for the ``status: failed`` record of a sweep job, so the report puts the
    failure in the right cell): reads only the dataset's ``meta.json`` and counts its
    training poses when the dataset is on disk; otherwise falls back to the scene config.
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


# ---------------------------------------------------------------------------- model
def build_field(model_cfg: DictConfig) -> Field:
    """The backbone of ``cfg.model``."""
    return instantiate(model_cfg, "model", Field, skip=DESCRIPTIVE_KEYS)


def build_renderer(render_cfg: DictConfig, props: SceneProperties,
                   precision: str | int | None = None) -> Renderer:
    """The renderer of ``cfg.render`` with the scene's clipping cylinder; its images render
    under the autocast of the run's ``precision``
    (:func:`~eventrecon.config.precision.image_dtype`)."""
    renderer = instantiate(render_cfg, "render", Renderer, skip=("image_autocast",),
                           **props.cylinder)
    renderer.image_dtype = image_dtype(render_cfg, precision)
    return renderer


def build_loss(loss_cfg: DictConfig, props: SceneProperties) -> LossConfig:
    """The loss weights of ``cfg.loss`` with the data's ε and θ."""
    return instantiate(loss_cfg, "loss", LossConfig, skip=DESCRIPTIVE_KEYS,
                       eps=props.tonemap_eps, theta=props.threshold)


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
        batcher = RayBatcher(train, seg, decay=props.decay, bayer=props.bayer,
                             neg_ratio=cfg.data.neg_ratio, device=device)
    lr, weight_decay, eps = optim_numbers(cfg)
    step = StepConfig(n_rays=cfg.trainer.n_rays, lr=lr, weight_decay=weight_decay,
                      betas=adam_betas(cfg), eps=eps,
                      max_nonfinite=cfg.trainer.max_nonfinite, log_every=cfg.trainer.log_every,
                      seed=cfg.seed + 1000 * k, max_steps=int(cfg.trainer.max_steps),
                      lr_end_factor=lr_end_factor(cfg), lr_warmup=lr_warmup(cfg),
                      lr_decay_start=lr_decay_start(cfg))
    renderer = build_renderer(cfg.render, props, run_precision(cfg))
    field.set_scene_box(*renderer.cylinder.box())
    return EventNeRFModule(field, renderer, batcher, build_loss(cfg.loss, props), step)


def build_logger(cfg: DictConfig, save_dir: Path, version: str) -> Any:
    """The Lightning logger of ``cfg.logger`` writing to ``save_dir/<name>/<version>``
    (``False`` for ``logger=none``)."""
    if not cfg.logger or not cfg.logger.get("_target_"):
        return False
    return instantiate(cfg.logger, "logger", save_dir=str(save_dir), version=version)


def build_callbacks(cfg: DictConfig) -> list[Any]:
    """Extra Lightning callbacks of ``cfg.trainer.callbacks`` (a mapping name → node)."""
    nodes = cfg.trainer.get("callbacks") or {}
    return [instantiate(node, f"trainer.callbacks.{name}") for name, node in nodes.items()]


# ---------------------------------------------------------------------------- checkpoints
@dataclass(frozen=True)
class CheckpointInfo:
    """What a run needs to know of a checkpoint before Lightning restores it."""

    path: Path
    step: int
    meta: dict[str, Any]


def inspect_checkpoint(path: str | Path, field: Field) -> CheckpointInfo:
    """Open ``path`` once (memory-mapped) and check it is a checkpoint of ``field``'s class.

    Runs before ``trainer.fit(ckpt_path=...)`` so that a missing, corrupt or foreign
    checkpoint (another backbone's) is one line naming the file, not a traceback from
    Lightning's state-dict loading.
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
    meta = dict(state.get("eventrecon") or {})
    mine = field_class_name(field)
    theirs = meta.get("field_class", mine)
    if theirs != mine:
        raise InputError(path, "eventrecon.field_class",
                         f"a checkpoint of {mine} (this run's model)", theirs)
    return CheckpointInfo(path, int(state.get("global_step", -1)), meta)


def load_segment(cfg: DictConfig, props: SceneProperties, seg_dir: Path, ckpt: str = "last",
                 precision: str | int | None = None) -> tuple[Field, Renderer]:
    """Field and renderer of a trained segment from ``seg_dir/checkpoints/<ckpt>.ckpt``;
    the renderer carries the segment's own ``clip_scale`` (cylinder annealing state) and
    renders images under ``precision`` (default: :func:`run_precision` here)."""
    d = seg_dir / "checkpoints"
    path = d / f"{ckpt}.ckpt"
    if not path.exists():
        raise InputError(d, f"{ckpt}.ckpt", "a checkpoint of every segment", "missing")
    field = build_field(cfg.model)
    inspect_checkpoint(path, field)
    state = torch.load(path, map_location="cpu", weights_only=False)
    field.load_state_dict({k[6:]: v for k, v in state["state_dict"].items()
                           if k.startswith("field.")})
    renderer = build_renderer(cfg.render, props,
                              run_precision(cfg) if precision is None else precision)
    renderer.load_state_dict({k[9:]: v for k, v in state["state_dict"].items()
                              if k.startswith("renderer.")})
    field.set_scene_box(*renderer.cylinder.box())
    renderer.clip_scale = float(state.get("eventrecon", {}).get("clip_scale", 1.0))
    return field.eval(), renderer
