"""AEDAT4 recordings (iniVation DV) of one camera: events, APS frames, triggers.

Decoded with the ``aedat`` package. The first event stream and the first frame stream
are read; events keep their µs timestamps (uint64 in the file, int64 here) and must be
non-decreasing (a recording made after the master's timestamp reset). A frame's time is
its exposure midpoint when the file records the exposure, else its timestamp. Frames
are read in a second pass by ordinal index, so a long recording is never held in memory
as images. A truncated or corrupt file is one :class:`~eventrecon.common.errors.InputError`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from eventrecon.common.errors import InputError

__all__ = ["Recording", "decode_aedat4", "read_frames"]


@dataclass
class Recording:
    """One camera's AEDAT4 recording (events in full, frames by timestamp only).

    Attributes:
        path: the file.
        width, height: the event sensor size.
        t, x, y: ``[N]`` uint64 µs / uint16 coordinates of the events, in file order.
        on: ``[N]`` bool polarity (``True`` = ON = +1).
        frame_t: ``[M]`` int64 µs timestamp of each APS frame (exposure midpoint).
        triggers: ``[T]`` structured array (``t``, ``source``).
    """

    path: Path
    width: int
    height: int
    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    on: np.ndarray
    frame_t: np.ndarray
    triggers: np.ndarray


def _is_decode_error(e: BaseException) -> bool:
    """aedat raises RuntimeError, or a Rust panic (``pyo3_runtime.PanicException``, a
    BaseException) on malformed flatbuffers; both mean a corrupt file."""
    return (isinstance(e, (RuntimeError, ValueError, OSError))
            or type(e).__name__ == "PanicException")


def _decoder(path: Path):
    import aedat

    if not path.is_file():
        raise InputError(path, "<file>", "an existing AEDAT4 recording", "missing")
    try:
        return aedat.Decoder(str(path))
    except BaseException as e:  # noqa: B036 -- Rust panics are BaseExceptions
        if not _is_decode_error(e):
            raise
        raise InputError(path, "<file>", "a readable AEDAT4 recording",
                         str(e).splitlines()[0][:60]) from None


def _frame_time(frame: dict) -> int:
    b, e = int(frame.get("exposure_begin_t", 0)), int(frame.get("exposure_end_t", 0))
    return (b + e) // 2 if e > b > 0 else int(frame["t"])


def decode_aedat4(path: str | Path) -> Recording:
    """Decode events, frame timestamps and triggers of the first event/frame streams."""
    path = Path(path)
    dec = _decoder(path)
    streams = dec.id_to_stream()
    ev_ids = sorted(i for i, s in streams.items() if s["type"] == "events")
    fr_ids = sorted(i for i, s in streams.items() if s["type"] == "frame")
    if not ev_ids:
        raise InputError(path, "streams", "an event stream",
                         sorted(s["type"] for s in streams.values()))
    ev_id, fr_id = ev_ids[0], (fr_ids[0] if fr_ids else None)
    w, h = int(streams[ev_id]["width"]), int(streams[ev_id]["height"])
    events, frame_t, triggers = [], [], []
    try:
        for packet in dec:
            sid = packet["stream_id"]
            if sid == ev_id and "events" in packet:
                events.append(packet["events"])
            elif sid == fr_id and "frame" in packet:
                frame_t.append(_frame_time(packet["frame"]))
            elif "triggers" in packet:
                triggers.append(packet["triggers"])
    except BaseException as e:  # noqa: B036
        if not _is_decode_error(e):
            raise
        raise InputError(path, "<file>", "a complete AEDAT4 recording",
                         str(e).splitlines()[0][:60]) from None
    ev = np.concatenate(events) if events else np.zeros(0, [("t", "<u8"), ("x", "<u2"),
                                                            ("y", "<u2"), ("on", "?")])
    t = np.ascontiguousarray(ev["t"]).astype(np.int64)
    if t.size > 1 and (np.diff(t) < 0).any():
        i = int(np.flatnonzero(np.diff(t) < 0)[0])
        raise InputError(path, "events.t", "non-decreasing timestamps (record after the "
                         "master's timestamp reset)", f"{t[i]} then {t[i + 1]} µs")
    x, y = np.ascontiguousarray(ev["x"]), np.ascontiguousarray(ev["y"])
    if x.size and (int(x.max()) >= w or int(y.max()) >= h):
        raise InputError(path, "events.x/y", f"inside the {w}×{h} sensor",
                         f"max ({int(x.max())}, {int(y.max())})")
    trig = np.concatenate(triggers) if triggers else np.zeros(0, [("t", "<u8"), ("source", "u1")])
    return Recording(path, w, h, t, x, y, np.ascontiguousarray(ev["on"]),
                     np.asarray(frame_t, np.int64), trig)


def read_frames(path: str | Path, indices: Sequence[int]) -> dict[int, np.ndarray]:
    """The APS frames with the given ordinal indices (second pass over the file).

    Returns ``{index: [H, W, 3] or [H, W] uint8}`` (RGB, or greyscale/Bayer raw).
    """
    path = Path(path)
    dec = _decoder(path)
    fr_ids = sorted(i for i, s in dec.id_to_stream().items() if s["type"] == "frame")
    want, out, k = set(int(i) for i in indices), {}, 0
    if not want:
        return out
    for packet in dec:
        if fr_ids and packet["stream_id"] == fr_ids[0] and "frame" in packet:
            if k in want:
                px = np.asarray(packet["frame"]["pixels"], np.uint8)
                out[k] = px[..., :3] if px.ndim == 3 else px
            k += 1
            if len(out) == len(want):
                break
    return out
