"""Which part of a dataset a run uses: its training views, RGB frames and held-out split.

The ablations of supplementary Tab. 5–7 train on fewer RGB frames (``data.fps``) or
fewer views (``data.views``) of the same scene; both selections are made here, on the
loaded split, so every other part of the run sees an ordinary (smaller) split. A time
``data.window`` (the authors' real-data runs train and evaluate one 120-unit window of
the clip, e.g. [90, 210] for Tab. 4) is the run's segment unless ``data.segments`` is
set (the "w/o multi-segment" row trains [0, 1000] and is evaluated on the window), and
only its ground-truth frames are scored.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from eventrecon.common.errors import InputError
from eventrecon.data.types import Dataset, SplitData

__all__ = ["heldout_split", "check_training_split", "select_views", "select_fps",
           "training_split", "window_frames"]


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
    """An evenly spread subset of ``n`` views of the ring (all when ``n`` is None):
    views ``floor(k·V/n)``, ``k = 0..n−1``."""
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
        masks=None if split.masks is None else split.masks[:, idx],
        loss_mask=None if split.loss_mask is None else split.loss_mask[idx])


def select_fps(split: SplitData, fps: float | None, duration_s: float,
               window: tuple[float, float] = (0.0, 1000.0)) -> SplitData:
    """The frames nearest to the grid ``start + k · 1000 / (fps · duration_s)`` of the time
    ``window = (start, end)`` (time units), ``k < fps · D_w`` with ``D_w`` the window's
    length in seconds.

    A rate ``F`` over ``D_w`` seconds keeps ``max(1, floor(F·D_w))`` frames (the grid is
    half-open, like a camera's shutter): 0.5 FPS over 2 s is one set of frames, as in the
    supplementary's 0.5 FPS row of Tab. 5, and so is 0.5 FPS over a 0.5 s window. The
    dataset's own rate keeps every frame.
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
    start, end = float(window[0]), float(window[1])
    seconds = duration_s * (end - start) / 1000.0
    n = max(1, int(math.floor(fps * seconds + 1e-9)))
    grid = start + np.arange(n) * step
    keep = sorted({int(np.argmin(np.abs(times - g))) for g in grid})
    return replace(split, frame_times=times[keep], frames=split.frames[keep],
                   masks=None if split.masks is None else split.masks[keep])


def training_split(ds: Dataset, views: int | None, fps: float | None,
                   duration_s: float | None,
                   window: tuple[float, float] = (0.0, 1000.0)) -> SplitData:
    """``ds``'s training split with ``views`` views and ``fps`` RGB frames per second (on a
    grid starting at the ``window``'s start), checked to have events and frames
    (:func:`check_training_split`)."""
    if "train" not in ds.splits:
        raise InputError(ds.root, "train/", "a training split")
    check_training_split(ds.splits["train"])
    train = select_views(ds.splits["train"], views)
    if fps is not None and duration_s is None:
        raise InputError("config", "data.duration_s", "the clip's length in seconds (data.fps "
                         "needs it; the dataset's meta.json does not say)", "missing")
    return select_fps(train, fps, duration_s or 1.0, window)


def window_frames(split: SplitData, window: tuple[float, float] | None,
                  every: int = 1) -> list[int]:
    """Indices of the split's frames inside ``window`` (all without one), every ``every``-th.

    >>> from types import SimpleNamespace
    >>> s = SimpleNamespace(frame_times=np.arange(0, 1001, 50.0))
    >>> window_frames(s, (90, 210)), len(window_frames(s, None, every=2))
    ([2, 3, 4], 11)
    """
    times = np.asarray(split.frame_times, dtype=np.float64)
    idx = (np.arange(len(times)) if window is None else
           np.flatnonzero((times >= window[0]) & (times <= window[1])))
    return [int(i) for i in idx[::max(1, int(every))]]
