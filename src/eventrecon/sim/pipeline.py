"""From a scene config to a dataset on disk: :func:`simulate_dataset`, :func:`ensure_dataset`.

``simulate_dataset`` builds the training split (ring or camdict cameras, events with the
scene's event effects, RGB frames with its frame effects, backgrounds, subject masks)
and the held-out ``validation`` split (cameras, sharp ground-truth renders at
``eval_fps``, sharp backgrounds, subject masks; no events) plus ``meta`` (the keys of
:class:`~eventrecon.data.types.Dataset`:
``tonemap_eps, threshold, decay, bayer, duration_s, cylinder, segments, scene, effects``,
and sampling statistics under ``sim``).

``ensure_dataset`` keys the result by a hash of the resolved scene config (and the
simulator version) and writes it atomically, only when missing.
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import torch

from eventrecon.common.locks import exclusive
from eventrecon.data.types import Dataset, SplitData
from eventrecon.data.writer import write_dataset
from eventrecon.sim.config import config_hash, to_plain
from eventrecon.sim.event_sim import simulate_events
from eventrecon.sim.frames import render_backgrounds, render_frames, render_masks
from eventrecon.sim.raytrace import PixelRenderer
from eventrecon.sim.spec import SceneSpec, build_cameras, frame_times, parse_spec

__all__ = ["simulate_dataset", "ensure_dataset", "dataset_path", "torch_threads", "SIM_VERSION"]

log = logging.getLogger(__name__)

#: Bumped whenever the simulator's output for a given config changes (part of the hash).
#: 2: both splits carry subject masks (``mask/<frame>/<view>.png``); datasets cached by
#: version 1 have none and are never reused. 3: the event core finds the crossings where
#: the signal turns (curvature bound, refined extrema) and frames may be area-averaged
#: (``frame_supersample``). 4: the training background plate averages
#: ``background_exposures`` exposures (a single noisy frame before). 5: the intrinsics
#: files put pixel centres at ``i + 0.5``, as the authors' code reads them
#: (:data:`eventrecon.render.cameras.FILE_PIXEL_CENTRE`); the simulated pixels are unchanged.
#: 6: event times on the quintic through the leg and two neighbours a side
#: (:mod:`eventrecon.sim.crossing`; the cubic through one a side before). 7: the core
#: keeps five path points and holds back two legs, so a block's edge legs have them too.
SIM_VERSION: int = 7


def _meta(spec: SceneSpec, stats: dict) -> dict:
    return {
        "tonemap_eps": spec.tonemap_eps, "threshold": spec.threshold, "decay": spec.decay,
        "bayer": spec.bayer, "duration_s": spec.duration_s, "cylinder": spec.cylinder,
        "segments": spec.segments, "rgb_fps": spec.rgb_fps, "eval_fps": spec.eval_fps,
        "scene": to_plain(spec.raw),
        "effects": {"events": [e.config() for e in spec.event_effects],
                    "frames": [e.config() for e in spec.frame_effects]},
        "sim": {"version": SIM_VERSION, **stats},
        "masks": "subject: the nearest hit is a moving or subject: true object",
        "grey_events": "log(mean(R, G, B) + tonemap_eps)" if not spec.bayer else None,
    }


@contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Temporarily set torch's intra-op CPU threads (``None``: leave as is).

    The simulator renders many small batches (the pixels still being refined); for
    those, intra-op threading costs more than it gains -- on a busy 2-core machine a
    whole simulation ran 10× faster with one thread.
    """
    if n is None:
        yield
        return
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def simulate_dataset(cfg: object, root: str | Path = ".", threads: int | None = 1) -> Dataset:
    """Simulate a scene config in memory (``root`` is only recorded in the result).

    ``threads``: torch CPU threads while simulating (see :func:`torch_threads`).
    """
    with torch_threads(threads):
        return _simulate(parse_spec(cfg), root)


def _simulate(spec: SceneSpec, root: str | Path) -> Dataset:
    t0 = time.perf_counter()
    train_cams, held_cams = build_cameras(spec)
    train_r = PixelRenderer(spec.scene, train_cams, spec.supersample)
    streams, core = simulate_events(spec, train_r)
    t_ev = time.perf_counter() - t0
    rgb_t = frame_times(spec.duration_s, spec.rgb_fps, spec.where, "rgb_fps")
    frames_r = (train_r if spec.frame_supersample == spec.supersample
                else PixelRenderer(spec.scene, train_cams, spec.frame_supersample))
    frames = render_frames(spec, frames_r, rgb_t, effects=True)
    train = SplitData(Path(root) / "train", train_cams, streams, rgb_t, frames,
                      background=render_backgrounds(spec, frames_r, effects=True),
                      masks=render_masks(frames_r, rgb_t))
    splits = {"train": train}
    if len(held_cams):
        held_r = PixelRenderer(spec.scene, held_cams, spec.frame_supersample)
        gt_t = frame_times(spec.duration_s, spec.eval_fps, spec.where, "eval_fps")
        splits["validation"] = SplitData(
            Path(root) / "validation", held_cams, None, gt_t,
            render_frames(spec, held_r, gt_t, effects=False),
            background=render_backgrounds(spec, held_r, effects=False),
            masks=render_masks(held_r, gt_t))
    n_ev = int(sum(len(s) for s in streams))
    stats = {"events": n_ev, "ideal_events": int(core.t.size), "pixel_samples": core.n_samples,
             "forced_steps": core.n_forced, "dynamic_pixels": core.extra["dynamic_pixels"]}
    # timings go to the log only: meta.json must be byte-identical for the same seed
    log.info("simulated %s: %d views, %d events, %d frames in %.1f s (events %.1f s)",
             spec.name, len(train_cams), n_ev, len(rgb_t), time.perf_counter() - t0, t_ev)
    return Dataset(Path(root), splits, _meta(spec, stats))


def dataset_path(scene_cfg: object, data_dir: str | Path = "data") -> Path:
    """``data_dir/<name>-<hash>``: where :func:`ensure_dataset` keeps this config.

    The hash covers the scene config and, for ``rig.camdict``, the camdict file's bytes
    (an edited calibration is a new dataset, not the cached one).
    """
    raw = to_plain(scene_cfg)
    name = str(raw.get("name", "scene")) if isinstance(raw, dict) else "scene"
    rig = raw.get("rig") if isinstance(raw, dict) else None
    if isinstance(rig, dict) and rig.get("camdict") and Path(rig["camdict"]).is_file():
        digest = hashlib.sha256(Path(rig["camdict"]).read_bytes()).hexdigest()
        raw = {**raw, "rig": {**rig, "camdict_sha256": digest}}
    return Path(data_dir) / f"{name}-{config_hash(raw, SIM_VERSION)}"


def ensure_dataset(scene_cfg: object, data_dir: str | Path = "data",
                   threads: int | None = 1, force: bool = False) -> Path:
    """Path of the simulated dataset of ``scene_cfg``; simulate and write it if missing.

    The folder appears atomically (temporary folder + rename), so a crash or Ctrl-C
    leaves no partial dataset behind and the next call simply simulates again. Parallel
    callers (a joblib sweep) serialise on an exclusive lock file beside the folder: the
    first simulates, the others wait and then find it. ``force`` simulates again and
    swaps the new folder in atomically (the old one stays intact until then).
    """
    path = dataset_path(scene_cfg, data_dir)
    if (path / "meta.json").is_file() and not force:
        log.info("dataset %s exists; not simulating again", path)
        return path
    with exclusive(path.parent / LOCKS / f"{path.name}.lock"):
        if (path / "meta.json").is_file() and not force:  # written while we waited
            return path
        ds = simulate_dataset(scene_cfg, path, threads=threads)
        write_dataset(ds, path, overwrite=path.exists())
    log.info("wrote %s", path)
    return path


#: Folder (inside the data folder) of the lock files of :func:`ensure_dataset`.
LOCKS = ".locks"


