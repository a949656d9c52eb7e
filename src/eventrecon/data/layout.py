"""Reader of the published dataset layout (one scene = ``train``/``validation`` splits).

Per split folder (docs/method.md, "Data layout of the published dataset")::

    intrinsics/<view>.txt        5×5 (K + k1 k2 p1 p2 k3), 5×4, 4×4 (or 3×3)
    pose/<view>.txt              4×4 rigid camera-to-world, OpenCV axes
    events/<view>.npz            x, y (int), t (float, 0..1000), p (±1)   [optional]
    rgb/<frame>/<view>.png       one folder per frame, named by its time unit [optional]
    background/<view>.png        empty-scene frame per view                [optional]
    mask/<frame>/<view>.png      foreground masks (or mask/<view>.png)     [optional]
                                 (a static mask/<view>.png also weights training losses)
    camdict.json                 per image: K, W2C (4×4 flat), dist, img_size

Rules:

- **Cameras.** ``intrinsics/`` + ``pose/`` take precedence over ``camdict.json``;
  when both exist they are compared and a disagreement (K, dist or c2w beyond 1e-4
  relative) is logged as a warning. With only ``camdict.json``, it defines the cameras.
- **Views** are matched by sorted file order in every folder. The match is checked:
  every folder must hold the same number of views, and the stems must agree view by
  view, comparing the trailing integer when a stem has one (``r_03`` matches ``03``
  and ``3``) and the whole stem otherwise.
- **Image size** comes from the PNGs (every image must have the same ``H × W``) or,
  without PNGs, from ``camdict.json``'s ``img_size``; both must agree.
- **Frames** ``[F, V, H, W, 3]`` uint8 (``[F, V, H, W]`` if the PNGs are single-channel
  Bayer raw), ``frame_times [F]`` parsed from the folder names, sorted by time.

Every violation raises :class:`eventrecon.common.errors.InputError` naming file and field.

>>> ds = read_dataset("data/scene")                    # doctest: +SKIP
>>> ds.splits["train"].frames.shape                    # doctest: +SKIP
(6, 6, 260, 346, 3)
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from eventrecon.common.errors import InputError
from eventrecon.common.progress import TaskProgress
from eventrecon.data.files import (
    RIGID_TOL,
    read_events_npz,
    read_intrinsics,
    read_json,
    read_png,
    read_pose,
)
from eventrecon.data.legacy import is_legacy_split
from eventrecon.data.types import Dataset, SplitData
from eventrecon.data.views import list_views, match_views
from eventrecon.events.stream import EventStream
from eventrecon.render.cameras import Cameras, cameras_from_camdict

__all__ = ["read_split", "read_dataset", "SPLITS"]

log = logging.getLogger(__name__)

#: Splits read by :func:`read_dataset` (when present), in this order. ``groundtruth`` is
#: the published synthetic scenes' folder of sharp held-out renders (same layout).
SPLITS: tuple[str, ...] = ("train", "validation", "groundtruth")

def _read_cameras(split: Path, rigid_tol: float) -> tuple[Cameras, list[str], Path]:
    """Cameras (width/height 0 while unknown), view names and the folder/file they came from."""
    intr, pose, camdict_path = split / "intrinsics", split / "pose", split / "camdict.json"
    from_camdict = None
    if camdict_path.is_file():
        try:
            from_camdict = cameras_from_camdict(read_json(camdict_path), camdict_path, rigid_tol)
        except InputError:
            raise
        except (TypeError, ValueError, RuntimeError, AttributeError) as e:
            raise InputError(camdict_path, "<entries>", "per-image objects with numeric K, "
                             "W2C (16 numbers), dist and img_size [W, H]",
                             f"{type(e).__name__}: {str(e)[:60]}") from None
    if not intr.is_dir() and not pose.is_dir():
        if from_camdict is None:
            raise InputError(split, "intrinsics/", "intrinsics/ and pose/ folders or a "
                             "camdict.json", "none found")
        return from_camdict, list(from_camdict.names), camdict_path
    for folder, what in ((intr, "intrinsics .txt files"), (pose, "4×4 pose .txt files")):
        if not folder.is_dir():
            raise InputError(folder, "<folder>", f"an existing folder of {what}", "missing")
    intr_files, pose_files = list_views(intr, ".txt"), list_views(pose, ".txt")
    if not intr_files:
        raise InputError(intr, "<folder>", "at least one <view>.txt", "empty folder")
    names = [f.stem for f in intr_files]
    match_views(names, intr, [f.stem for f in pose_files], pose)
    Ks, dists = zip(*(read_intrinsics(f) for f in intr_files))
    c2ws = [read_pose(f, rigid_tol) for f in pose_files]
    w, h = (from_camdict.width, from_camdict.height) if from_camdict else (0, 0)
    cams = Cameras(np.stack(Ks), np.stack(dists), np.stack(c2ws), w, h, names)
    if from_camdict is not None:
        match_views(names, intr, from_camdict.names, camdict_path)
        for attr in ("K", "dist", "c2w"):
            a, b = getattr(cams, attr), getattr(from_camdict, attr)
            if not np.allclose(a.numpy(), b.numpy(), rtol=1e-4, atol=1e-4):
                log.warning("%s: %s disagrees with intrinsics/ + pose/, which take precedence",
                            camdict_path, attr)
    return cams, names, intr


class _ImageSize:
    """Tracks the one ``(H, W)`` every image of a split must share (first image seen sets it)."""

    def __init__(self) -> None:
        self.hw: tuple[int, int] | None = None
        self.first: Path | None = None

    def check(self, img: np.ndarray, path: Path) -> np.ndarray:
        hw = (int(img.shape[0]), int(img.shape[1]))
        if self.hw is None:
            self.hw, self.first = hw, path
        elif hw != self.hw:
            raise InputError(path, "image size",
                             f"H×W = {self.hw[0]}×{self.hw[1]} as {self.first}",
                             f"{hw[0]}×{hw[1]}")
        return img


def _frame_folders(root: Path) -> list[tuple[float, Path]]:
    """``(time, folder)`` of the per-frame folders under ``rgb/`` or ``mask/``, by time."""
    out = []
    for d in root.iterdir():
        if d.name.startswith("."):
            continue
        if not d.is_dir():
            raise InputError(d, "<layout>", f"per-frame folders {root.name}/<time>/<view>.png",
                             "a file")
        try:
            out.append((float(d.name), d))
        except ValueError:
            raise InputError(d, "frame time", "a folder named by its time unit (e.g. 0200)",
                             repr(d.name)) from None
    return sorted(out, key=lambda tf: tf[0])


def _read_view_images(folder: Path, names: list[str], ref: Path, size: _ImageSize) -> np.ndarray:
    """``[V, H, W(, 3)]`` uint8 from ``folder/<view>.png`` (views checked against ``names``)."""
    files = list_views(folder, ".png")
    match_views(names, ref, [f.stem for f in files], folder)
    imgs = [size.check(read_png(f), f) for f in files]
    for f, im in zip(files, imgs):
        if im.ndim != imgs[0].ndim:
            raise InputError(f, "channels", f"the channel layout of {files[0]}",
                             f"{im.ndim}-D image")
    return np.stack(imgs)


def _read_frames(split: Path, names: list[str], ref: Path,
                 size: _ImageSize) -> tuple[np.ndarray, np.ndarray]:
    rgb = split / "rgb"
    if not rgb.is_dir():
        return np.zeros(0, np.float64), np.zeros((0, len(names), 0, 0, 3), np.uint8)
    folders = _frame_folders(rgb)
    times = np.array([t for t, _ in folders], np.float64)
    progress = TaskProgress(f"reading {split.name} frames", len(folders))
    frames = []
    for _, d in folders:
        frames.append(_read_view_images(d, names, ref, size))
        progress.step()
    for (_, d), fr in zip(folders, frames):
        if fr.ndim != frames[0].ndim:
            raise InputError(d, "channels", f"the channel layout of {folders[0][1]}",
                             f"{fr.ndim - 1}-D images")
    if not frames:
        return times, np.zeros((0, len(names), 0, 0, 3), np.uint8)
    return times, np.stack(frames)


def _read_masks(split: Path, names: list[str], ref: Path, times: np.ndarray,
                size: _ImageSize) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(masks, loss_mask)``: ``[F, V, H, W]`` bool from per-frame ``mask/<time>/<view>.png``
    or static ``mask/<view>.png``, and for static masks only the training-loss weights
    ``[V, H, W]`` float32 = first channel / 255 (the authors' reading; ``SplitData``)."""
    mask = split / "mask"
    if not mask.is_dir():
        return None, None
    if any(f.is_file() and f.suffix.lower() == ".png" for f in mask.iterdir()):
        per_view = _read_view_images(mask, names, ref, size)
        m = per_view > 127 if per_view.ndim == 3 else (per_view > 127).any(-1)
        weight = (per_view if per_view.ndim == 3 else per_view[..., 0]).astype(np.float32) / 255
        return np.broadcast_to(m, (len(times), *m.shape)).copy(), weight
    folders = _frame_folders(mask)
    mt = np.array([t for t, _ in folders], np.float64)
    if mt.shape != times.shape or not np.allclose(mt, times):
        raise InputError(mask, "frame times", f"the frame folders of rgb/ ({times.tolist()})",
                         mt.tolist())
    out = []
    for _, d in folders:
        im = _read_view_images(d, names, ref, size)
        out.append(im > 127 if im.ndim == 3 else (im > 127).any(-1))
    return np.stack(out), None


def read_split(path: str | Path, *, binary_polarity: bool = False,
               rigid_tol: float = RIGID_TOL) -> SplitData:
    """Read and validate one split folder of the published layout.

    Args:
        path: the split folder (``<scene>/train``).
        binary_polarity: accept polarities stored as ``{0, 1}`` (mapped to ``2p − 1``);
            by default only ``±1`` is accepted.
        rigid_tol: tolerance of the rigid-pose check.

    Returns:
        :class:`SplitData` with cameras ``[V]`` (view order = sorted file order), events
        (one time-sorted :class:`EventStream` per view, or ``None`` without ``events/``),
        ``frame_times [F]``, ``frames [F, V, H, W, 3]`` uint8 (``[F, V, H, W]`` for
        single-channel raw), ``background [V, H, W(, 3)]`` or ``None``, masks
        ``[F, V, H, W]`` bool or ``None``, and ``loss_mask [V, H, W]`` for a static
        ``mask/<view>.png`` (:class:`~eventrecon.data.types.SplitData`).

    Raises:
        InputError: for any missing, malformed or inconsistent file (one line naming it).
    """
    split = Path(path)
    if not split.is_dir():
        raise InputError(split, "<folder>", "an existing split folder", "missing")
    if is_legacy_split(split):
        raise InputError(split, "<layout>", "the multi-view layout (one events npz per view)",
                         "the earlier single-camera EventNeRF layout; read it with "
                         "eventrecon.data.legacy.read_legacy_split")
    cams, names, ref_path = _read_cameras(split, rigid_tol)
    size = _ImageSize()
    times, frames = _read_frames(split, names, ref_path, size)
    background = None
    if (split / "background").is_dir():
        background = _read_view_images(split / "background", names, ref_path, size)
    masks, loss_mask = _read_masks(split, names, ref_path, times, size)
    if size.hw is not None:
        h, w = size.hw
        if cams.width and (cams.width, cams.height) != (w, h):
            raise InputError(split / "camdict.json", "img_size", f"[{w}, {h}] as the PNGs",
                             [cams.width, cams.height])
    elif cams.width:
        h, w = cams.height, cams.width
    else:
        raise InputError(split, "image size", "PNGs under rgb/ or background/, or "
                         "camdict.json with img_size", "neither")
    cams.width, cams.height = w, h
    if frames.shape[0] == 0:
        frames = np.zeros((0, len(names), h, w, 3), np.uint8)
    events: list[EventStream] | None = None
    if (split / "events").is_dir():
        ev_files = list_views(split / "events", ".npz")
        match_views(names, ref_path, [f.stem for f in ev_files], split / "events")
        events = [read_events_npz(f, w, h, binary_polarity=binary_polarity) for f in ev_files]
    log.info("read %s: %d views %dx%d, %d frames, %s events", split, len(names), w, h,
             len(times), "no" if events is None else sum(len(e) for e in events))
    return SplitData(root=split, cameras=cams, events=events, frame_times=times,
                     frames=frames, background=background, masks=masks, loss_mask=loss_mask)


def read_dataset(root: str | Path, *, binary_polarity: bool = False,
                 rigid_tol: float = RIGID_TOL) -> Dataset:
    """Read a scene: the splits of :data:`SPLITS` that exist, plus ``meta.json``.

    Args:
        root: the scene folder holding ``train/`` (required), ``validation/`` and, for
            the published synthetic scenes, ``groundtruth/``.
        binary_polarity, rigid_tol: as in :func:`read_split`.

    Returns:
        :class:`Dataset` with ``splits`` and ``meta`` (``{}`` without ``meta.json``).
    """
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, "<folder>", "an existing scene folder", "missing")
    if not (root / SPLITS[0]).is_dir():
        raise InputError(root / SPLITS[0], "<folder>", "a train/ split folder", "missing")
    meta: dict = {}
    if (root / "meta.json").is_file():
        meta = read_json(root / "meta.json")
        if not isinstance(meta, dict):
            raise InputError(root / "meta.json", "<root>", "a JSON object",
                             type(meta).__name__)
    splits = {s: read_split(root / s, binary_polarity=binary_polarity, rigid_tol=rigid_tol)
              for s in SPLITS if (root / s).is_dir()}
    return Dataset(root=root, splits=splits, meta=meta)
