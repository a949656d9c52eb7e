"""Recordings of the camera rig converted into the published dataset layout.

:func:`convert_aedat4` (``python -m eventrecon.convert aedat4 --inputs cam0.aedat4 …
cam5.aedat4 --out DIR [--start-us S] [--end-us E] [--fps 5] [--background-us B]
[--camdict camdict.json] [--segments 5] [--sync-tolerance-us 100]``

One AEDAT4 recording per camera (:mod:`eventrecon.data.aedat4`: events, APS frames,
triggers). The steps:

1. **Align.** The cameras are hardware-synchronised (sync cable; a timestamp reset on
   the master resets the slaves), so one µs timestamp is one instant on every camera.
   The shared span is ``[max_i first_i, min_i last_i]`` over the cameras' events.
2. **Cut.** ``--start-us``/``--end-us``/``--background-us`` are offsets in µs from the
   start of the shared span (defaults: the whole span). Events with
   ``start ≤ t ≤ end`` are kept.
3. **Normalise.** ``t ← (t − start) · 1000 / (end − start)`` in float64 (integer µs
   differences first, so no precision is lost before the division).
4. **Frames.** Target times ``start + k · 10⁶/fps`` (``k = 0, 1, …`` while ``≤ end``);
   each camera contributes its APS frame whose timestamp (exposure midpoint when the
   file records the exposure, else the frame timestamp) is nearest the target. The
   frame folder is named by the target's time unit. Colour frames are stored as RGB
   PNGs, greyscale (Bayer raw) frames as single-channel PNGs.
5. **Background.** Per camera the APS frame nearest ``--background-us`` (the empty
   scene), stored as ``background/<view>.png``.
6. **Triggers.** Every camera's trigger stream inside the cut goes to ``meta.json``
   (``triggers[<view>] = {t, t_us, source}``, ``t`` normalised like the events). The
   external triggers (sources 1–5: signal and generator edges and pulses) are one
   physical pulse seen by every camera, so they also check the synchronisation: if all
   cameras recorded the same number of them, the k-th one must carry the same timestamp
   everywhere (within ``--sync-tolerance-us``, 100 µs by default), else one line names
   the first camera and trigger that disagree.

Views are named ``00, 01, …`` in ``--inputs`` order; ``meta.json`` records the source
files, the span, the chosen frame timestamps, the triggers and the real-data defaults
(``tonemap_eps`` 3e-2, ``threshold`` 0.5, ``decay`` 0.93, Bayer, ``--segments`` equal
overlapping segments, 5 by default). Cameras come from ``--camdict`` (copied after
validation); the output is written to a temporary folder and renamed (atomic).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from eventrecon import TIME_SPAN
from eventrecon.common.errors import InputError
from eventrecon.data.aedat4 import Recording, decode_aedat4, read_frames
from eventrecon.data.segments import make_segments
from eventrecon.render.cameras import load_camdict

__all__ = ["shared_span", "check_trigger_sync", "nearest_frames", "convert_aedat4"]

log = logging.getLogger(__name__)


def shared_span(recordings: Sequence[Recording]) -> tuple[int, int]:
    """``(max first event µs, min last event µs)`` over the cameras."""
    for r in recordings:
        if r.t.size == 0:
            raise InputError(r.path, "events", "at least one event", "none")
    s0 = max(int(r.t[0]) for r in recordings)
    s1 = min(int(r.t[-1]) for r in recordings)
    if s1 <= s0:
        raise InputError(recordings[0].path, "time span",
                         "recordings that overlap in time (same synchronised clock)",
                         f"shared span [{s0}, {s1}] µs")
    return s0, s1


#: Trigger sources that are external pulses (DV ``TriggerType`` 1–5): the same physical
#: event on every synchronised camera.
EXTERNAL_TRIGGERS: frozenset[int] = frozenset({1, 2, 3, 4, 5})


def check_trigger_sync(recordings: Sequence[Recording], tolerance_us: int = 100) -> int | None:
    """Compare the external triggers of synchronised cameras; return the largest spread.

    Only the triggers inside the shared span (every camera recording) are compared, so
    cameras started or stopped at different times still check. Returns ``None`` when the
    check does not apply (a camera has no external trigger in the span, or the cameras
    saw different numbers of them there: logged, not compared).

    Raises:
        InputError: the k-th external trigger differs by more than ``tolerance_us``
            between the first camera and another one (the clocks are not synchronised).
    """
    s0, s1 = shared_span(recordings)
    ext = []
    for r in recordings:
        t = r.triggers["t"][np.isin(r.triggers["source"], list(EXTERNAL_TRIGGERS))]
        t = t.astype(np.int64)
        ext.append(np.sort(t[(t >= s0 - tolerance_us) & (t <= s1 + tolerance_us)]))
    if not ext or any(e.size == 0 for e in ext):
        return None
    if len({e.size for e in ext}) != 1:
        log.warning("external triggers in the shared span differ in number between cameras "
                    "(%s): synchronisation not checked", [int(e.size) for e in ext])
        return None
    spread = [np.abs(e - ext[0]) for e in ext]
    worst = max(int(d.max()) for d in spread)
    if worst > tolerance_us:
        cam = next(i for i, d in enumerate(spread) if int(d.max()) == worst)
        k = int(np.argmax(spread[cam]))
        raise InputError(recordings[cam].path, "triggers",
                         f"external trigger {k} at the time of {recordings[0].path.name}'s "
                         f"(±{tolerance_us} µs: synchronised clocks)",
                         f"{int(ext[cam][k])} vs {int(ext[0][k])} µs")
    return worst


def nearest_frames(frame_t: np.ndarray, targets_us: np.ndarray) -> np.ndarray:
    """``[T]`` index of the frame whose timestamp is nearest each target (ties: earlier).

    >>> nearest_frames(np.array([0, 100, 200]), np.array([-5, 49, 50, 51, 999]))
    array([0, 0, 0, 1, 2])
    """
    if len(frame_t) < 2:
        return np.zeros(len(targets_us), np.int64)
    j = np.clip(np.searchsorted(frame_t, targets_us), 1, len(frame_t) - 1)
    left, right = frame_t[j - 1], frame_t[j]
    return np.where(targets_us - left <= right - targets_us, j - 1, j)


def _time_name(t: float) -> str:
    r = round(t)
    return f"{r:04d}" if abs(t - r) < 1e-6 else f"{t:09.4f}"


def convert_aedat4(inputs: Sequence[str | Path], out: str | Path, start_us: int = 0,
                   end_us: int | None = None, fps: float = 5.0,
                   background_us: int | None = None, camdict: str | Path | None = None,
                   split: str = "train", bayer: bool = True, overwrite: bool = False,
                   segments: int = 5, sync_tolerance_us: int = 100) -> Path:
    """Convert one AEDAT4 recording per camera into ``out/<split>/`` (module docstring).

    Args:
        inputs: ``V`` recordings, one per camera (view ``i`` = ``inputs[i]``).
        out: the scene folder to create.
        start_us, end_us: the cut, µs from the start of the shared span
            (``end_us=None``: to the end of the shared span).
        fps: RGB reference frames per second.
        background_us: time of the empty scene (µs from the shared-span start), or None.
        camdict: the rig's ``camdict.json`` (``V`` entries, sensor-sized), or None.
        split: split folder name.
        bayer: whether the event pixels are colour (Bayer) pixels (DAVIS 346C).
        overwrite: replace an existing ``out``.
        segments: number of equal overlapping training segments recorded in ``meta.json``.
        sync_tolerance_us: largest allowed disagreement of external triggers.

    Returns:
        The scene folder.
    """
    out = Path(out)
    if out.exists() and not overwrite:
        raise InputError(out, "<folder>", "a new output folder (or --overwrite)", "exists")
    recs = [decode_aedat4(p) for p in inputs]
    sizes = {(r.width, r.height) for r in recs}
    if len(sizes) != 1:
        raise InputError(recs[-1].path, "resolution", "the same sensor size for all cameras",
                         sorted(sizes))
    (w, h), = sizes
    s0, s1 = shared_span(recs)
    spread = check_trigger_sync(recs, sync_tolerance_us)
    if spread is not None:
        log.info("external triggers agree across the cameras within %d µs", spread)
    start = s0 + int(start_us)
    end = s1 if end_us is None else s0 + int(end_us)
    if not s0 <= start < end <= s1:
        raise InputError("--start-us/--end-us", "cut", f"0 ≤ start < end ≤ {s1 - s0} µs "
                         "(offsets within the shared span)", f"[{start_us}, {end_us}]")
    span = end - start
    n_frames = int(np.floor(span * fps / 1e6 + 1e-9)) + 1 if fps > 0 else 0
    targets = start + np.round(np.arange(n_frames) * 1e6 / fps).astype(np.int64) if n_frames else \
        np.zeros(0, np.int64)
    cams_json = None
    if camdict is not None:
        cams = load_camdict(camdict)
        if len(cams) != len(recs) or (cams.width, cams.height) != (w, h):
            raise InputError(camdict, "entries", f"{len(recs)} cameras of {w}×{h}",
                             f"{len(cams)} of {cams.width}×{cams.height}")
        cams_json = Path(camdict).read_text()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        cut = _Cut(start, end, s0, targets, None if background_us is None else s0 + background_us)
        _write(recs, tmp / split, cut)
        meta = {"source": [str(Path(p)) for p in inputs], "start_us": start, "end_us": end,
                "duration_s": (end - start) / 1e6, "fps": fps, "rgb_fps": fps,
                "tonemap_eps": 3e-2, "threshold": 0.5, "decay": 0.93, "bayer": bayer,
                "segments": [[sg.start, sg.end] for sg in make_segments(segments)],
                "background_us": cut.background,
                "triggers": {f"{v:02d}": _triggers_in(r, start, end) for v, r in enumerate(recs)}}
        meta.update(cut.log)
        if cams_json is not None:
            (tmp / split / "camdict.json").write_text(cams_json)
        (tmp / "meta.json").write_text(json.dumps(meta, indent=1))
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if out.exists():
        shutil.rmtree(out)
    os.replace(tmp, out)
    return out


def _triggers_in(rec: Recording, start: int, end: int) -> dict[str, list]:
    """The recording's triggers with ``start ≤ t ≤ end``: µs, normalised time, source."""
    trig = rec.triggers[(rec.triggers["t"] >= start) & (rec.triggers["t"] <= end)]
    t_us = trig["t"].astype(np.int64)
    return {"t_us": t_us.tolist(),
            "t": ((t_us - start).astype(np.float64) * TIME_SPAN / (end - start)).tolist(),
            "source": trig["source"].astype(int).tolist()}


@dataclass
class _Cut:
    """The chosen span and sample times, all in shared-clock µs."""

    start: int
    end: int
    s0: int
    targets: np.ndarray
    background: int | None
    log: dict = field(default_factory=lambda: {"frames_us": {}, "background_frames_us": []})


def _write(recs: Sequence[Recording], sp: Path, cut: _Cut) -> None:
    """Write events, frames and backgrounds of every camera into the split folder ``sp``."""
    span = cut.end - cut.start
    for v, r in enumerate(recs):
        name = f"{v:02d}"
        keep = slice(np.searchsorted(r.t, cut.start, "left"),
                     np.searchsorted(r.t, cut.end, "right"))
        t_norm = (r.t[keep] - cut.start).astype(np.float64) * TIME_SPAN / span
        (sp / "events").mkdir(parents=True, exist_ok=True)
        np.savez(sp / "events" / f"{name}.npz", x=r.x[keep].astype(np.int16),
                 y=r.y[keep].astype(np.int16), t=t_norm,
                 p=np.where(r.on[keep], 1, -1).astype(np.int8))
        wanted: dict[str, int] = {}
        if r.frame_t.size and len(cut.targets):
            for tgt, i in zip(cut.targets, nearest_frames(r.frame_t, cut.targets)):
                wanted[_time_name((tgt - cut.start) * TIME_SPAN / span)] = int(i)
        bg = None
        if cut.background is not None:
            if not r.frame_t.size:
                raise InputError(r.path, "frames", "APS frames for the background", "none")
            bg = int(nearest_frames(r.frame_t, np.array([cut.background]))[0])
        frames = read_frames(r.path, list(wanted.values()) + ([bg] if bg is not None else []))
        for folder, i in wanted.items():
            (sp / "rgb" / folder).mkdir(parents=True, exist_ok=True)
            iio.imwrite(sp / "rgb" / folder / f"{name}.png", frames[i])
        if bg is not None:
            (sp / "background").mkdir(parents=True, exist_ok=True)
            iio.imwrite(sp / "background" / f"{name}.png", frames[bg])
            cut.log["background_frames_us"].append(int(r.frame_t[bg]))
        cut.log["frames_us"][name] = [int(r.frame_t[i]) for i in wanted.values()]
        log.info("%s -> view %s: %d events, %d frames", r.path, name, keep.stop - keep.start,
                 len(wanted))
