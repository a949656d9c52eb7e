"""Reader of the earlier EventNeRF layout: one moving event camera along ~1000 poses.

Per split folder (the single-camera, static-scene data of the earlier work)::

    intrinsics/<i>.txt   one per pose (5×4, 4×4, 5×5 or 3×3), or a single file for all
    pose/<i>.txt         4×4 rigid camera-to-world of pose i (sorted file order)
    events/<name>.npz    exactly one file: x, y, t, p of the whole trajectory
    rgb/<i>.png          optional, one image per pose (flat, not per-frame folders)
    mask/<i>.png         optional, one mask per pose

**How poses are matched to times** (as the earlier loader does): the ``N`` poses are
equally spaced in time over the recording, pose ``i`` at ``t_max · i / (N − 1)`` with
``t_max`` the last event timestamp (timestamps start at 0). Here times are
rescaled to the platform's time units, ``t ← 1000 · t / t_max``, so pose ``i`` sits at
``τ_i = 1000 · i / (N − 1)``. An event at time ``t`` was recorded between poses
``⌊t (N−1)/1000⌋`` and the next; :meth:`LegacySplit.pose_at` interpolates the camera
there (linear translation, spherical-linear rotation), :meth:`LegacySplit.pose_index`
gives the nearest pose.

The result uses the platform's structures (:class:`Cameras`, :class:`EventStream`,
uint8 frames); because the camera moves, it is a :class:`LegacySplit`, not a
multi-view :class:`SplitData`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from eventrecon import TIME_SPAN
from eventrecon.common.errors import InputError
from eventrecon.data.files import RIGID_TOL, read_events_npz, read_intrinsics, read_png, read_pose
from eventrecon.data.views import list_views, match_views
from eventrecon.events.stream import EventStream
from eventrecon.render.cameras import Cameras

__all__ = ["LegacySplit", "read_legacy_split", "is_legacy_split", "slerp_c2w"]

log = logging.getLogger(__name__)

#: Sensor size the earlier loader assumed when a split has no images (DAVIS 346).
DEFAULT_SIZE: tuple[int, int] = (346, 260)


def slerp_c2w(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Interpolate rigid transforms: ``R = R_a · exp(w · log(R_aᵀ R_b))``, ``t`` linear.

    Args:
        a, b: ``[N, 4, 4]`` rigid camera-to-world matrices.
        w: ``[N]`` weights in [0, 1] (0 gives ``a``, 1 gives ``b``).

    Returns:
        ``[N, 4, 4]`` rigid matrices (Rodrigues' formula for the rotation).

    >>> rz = lambda th: np.array([[np.cos(th), -np.sin(th), 0, 0], [np.sin(th), np.cos(th), 0, 0],
    ...                           [0, 0, 1, 0], [0, 0, 0, 1]])
    >>> np.allclose(slerp_c2w(rz(0.0)[None], rz(1.0)[None], np.array([0.3]))[0], rz(0.3))
    True
    """
    rel = np.einsum("nji,njk->nik", a[:, :3, :3], b[:, :3, :3])
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    ang = np.arccos(cos)
    axis = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0],
                     rel[:, 1, 0] - rel[:, 0, 1]], -1)
    norm = np.linalg.norm(axis, axis=-1, keepdims=True)
    axis = np.where(norm > 1e-12, axis / np.maximum(norm, 1e-12), [[0.0, 0.0, 1.0]])
    th = w * ang
    kx = np.zeros((len(w), 3, 3))
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    kx = kx - kx.transpose(0, 2, 1)
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    step = np.eye(3) + s * kx + (1 - c) * (kx @ kx)
    out = np.tile(np.eye(4), (len(w), 1, 1))
    out[:, :3, :3] = a[:, :3, :3] @ step
    out[:, :3, 3] = (1 - w)[:, None] * a[:, :3, 3] + w[:, None] * b[:, :3, 3]
    return out


@dataclass
class LegacySplit:
    """One split of the earlier layout.

    Attributes:
        root: the split folder.
        poses: ``N`` cameras, one per pose (names = pose file stems).
        pose_times: ``[N]`` float64 time units ``1000 · i / (N − 1)``.
        events: the single time-sorted stream, ``t`` rescaled to [0, 1000].
        frames: ``[N, H, W, 3]`` uint8 (one per pose) or ``None``.
        masks: ``[N, H, W]`` bool or ``None``.
    """

    root: Path
    poses: Cameras
    pose_times: np.ndarray
    events: EventStream
    frames: np.ndarray | None = None
    masks: np.ndarray | None = None

    def pose_index(self, t: np.ndarray) -> np.ndarray:
        """``[M]`` index of the pose nearest each time ``t [M]`` (time units)."""
        n = len(self.pose_times)
        return np.clip(np.rint(np.asarray(t) / TIME_SPAN * (n - 1)), 0, n - 1).astype(np.int64)

    def pose_at(self, t: np.ndarray) -> torch.Tensor:
        """``[M, 4, 4]`` camera-to-world at times ``t [M]``, interpolated between poses."""
        n = len(self.pose_times)
        s = np.clip(np.asarray(t, np.float64) / TIME_SPAN * (n - 1), 0, n - 1)
        i0 = np.minimum(np.floor(s).astype(np.int64), n - 2) if n > 1 else np.zeros_like(s, int)
        c2w = self.poses.c2w.numpy()
        if n == 1:
            return torch.as_tensor(np.repeat(c2w, len(s), 0))
        return torch.as_tensor(slerp_c2w(c2w[i0], c2w[i0 + 1], s - i0))


def is_legacy_split(path: str | Path) -> bool:
    """True if ``path/events`` holds one npz while ``path/pose`` holds several poses."""
    path = Path(path)
    if not (path / "events").is_dir() or not (path / "pose").is_dir():
        return False
    if len(list_views(path / "events", ".npz")) != 1 or len(list_views(path / "pose", ".txt")) < 2:
        return False
    return not (path / "rgb").is_dir() or _flat_images(path / "rgb")


def _flat_images(folder: Path) -> bool:
    return any(f.is_file() and f.suffix.lower() == ".png" for f in folder.iterdir())


def _read_flat_images(folder: Path, names: list[str], ref: Path) -> np.ndarray:
    files = list_views(folder, ".png")
    match_views(names, ref, [f.stem for f in files], folder)
    imgs = [read_png(f) for f in files]
    for f, im in zip(files, imgs):
        if im.shape != imgs[0].shape:
            raise InputError(f, "image size", f"{imgs[0].shape} as {files[0]}", im.shape)
    return np.stack(imgs)


def read_legacy_split(path: str | Path, *, binary_polarity: bool = False,
                      rigid_tol: float = RIGID_TOL) -> LegacySplit:
    """Read one split of the earlier single-moving-camera layout (see the module docstring).

    Raises:
        InputError: missing folders, not exactly one events npz, pose/intrinsics count
            mismatch, bad matrices or events (same checks as :func:`read_split`).
    """
    split = Path(path)
    for sub in ("pose", "intrinsics", "events"):
        if not (split / sub).is_dir():
            raise InputError(split / sub, "<folder>", "an existing folder", "missing")
    pose_files = list_views(split / "pose", ".txt")
    if not pose_files:
        raise InputError(split / "pose", "<folder>", "at least one <i>.txt", "empty folder")
    names = [f.stem for f in pose_files]
    intr_files = list_views(split / "intrinsics", ".txt")
    if len(intr_files) != 1:
        match_views(names, split / "pose", [f.stem for f in intr_files], split / "intrinsics")
    ev_files = list_views(split / "events", ".npz")
    if len(ev_files) != 1:
        raise InputError(split / "events", "<folder>", "exactly one .npz for the moving camera",
                         f"{len(ev_files)} files")
    frames = masks = None
    if (split / "rgb").is_dir() and _flat_images(split / "rgb"):
        frames = _read_flat_images(split / "rgb", names, split / "pose")
    if (split / "mask").is_dir() and _flat_images(split / "mask"):
        m = _read_flat_images(split / "mask", names, split / "pose")
        masks = m > 127 if m.ndim == 3 else (m > 127).any(-1)
    w, h = (frames.shape[2], frames.shape[1]) if frames is not None else DEFAULT_SIZE
    n = len(names)
    Ks, dists = zip(*(read_intrinsics(f) for f in intr_files))
    Ks, dists = np.stack(Ks), np.stack(dists)
    if len(intr_files) == 1:
        Ks, dists = np.repeat(Ks, n, 0), np.repeat(dists, n, 0)
    c2w = np.stack([read_pose(f, rigid_tol) for f in pose_files])
    ev = read_events_npz(ev_files[0], w, h, binary_polarity=binary_polarity,
                         t_range=(0.0, np.inf))
    t_max = float(ev.t[-1]) if len(ev) else 1.0
    if t_max <= 0:
        raise InputError(ev_files[0], "t", "a recording spanning t > 0", f"t_max = {t_max}")
    ev.t = ev.t * (TIME_SPAN / t_max)
    pose_times = TIME_SPAN * np.arange(n) / max(n - 1, 1)
    log.info("read legacy split %s: %d poses, %d events, t_max %g -> 1000", split, n, len(ev),
             t_max)
    return LegacySplit(split, Cameras(Ks, dists, c2w, w, h, names), pose_times, ev, frames, masks)
