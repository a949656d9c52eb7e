"""Writer of the published dataset layout (the inverse of :mod:`eventrecon.data.layout`).

Per split folder::

    intrinsics/<view>.txt   5×5: K top-left 3×3, last row k1 k2 p1 p2 k3, rest 0
    pose/<view>.txt         4×4 camera-to-world (OpenCV axes)
    events/<view>.npz       x int16, y int16, t float64 (0..1000), p int8
    rgb/<frame:04d>/<view>.png   folder = frame time unit, rounded
    background/<view>.png
    camdict.json            per image "<view>.png": K (4×4 flat), W2C, dist, img_size

and ``<root>/meta.json`` for a :class:`~eventrecon.data.types.Dataset`.

Output is byte-reproducible: numbers are written with ``repr`` (exact float64
round-trip), JSON with sorted keys, npz archives with a fixed zip timestamp (NumPy's
``savez`` stamps the current time), PNGs without time chunks. Every write goes to a
temporary folder beside the target which is renamed into place only when complete, so
an interrupted run leaves no half-written split or scene.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import tempfile
import zipfile
from pathlib import Path

import numpy as np
from PIL import Image

from eventrecon.common.errors import InputError
from eventrecon.data.types import Dataset, SplitData
from eventrecon.events.stream import EventStream
from eventrecon.render.cameras import Cameras, K_to_file, cameras_to_camdict

__all__ = ["write_split", "write_dataset", "write_npz", "write_matrix", "frame_folder"]

_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


def frame_folder(t: float) -> str:
    """Folder name of a frame at time unit ``t``: ``round(t)`` with 4 digits."""
    return f"{int(round(float(t))):04d}"


def write_matrix(path: Path, m: np.ndarray) -> None:
    """A matrix as whitespace-separated exact (``repr``) float64 rows."""
    rows = [" ".join(repr(float(v)) for v in row) for row in np.atleast_2d(m)]
    path.write_text("\n".join(rows) + "\n")


def write_npz(path: Path, **arrays: np.ndarray) -> None:
    """``np.savez`` layout with a fixed zip timestamp (byte-identical for equal arrays)."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as zf:
        for key, arr in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arr), allow_pickle=False)
            info = zipfile.ZipInfo(f"{key}.npy", date_time=_ZIP_EPOCH)
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue())


def _write_png(path: Path, img: np.ndarray) -> None:
    if img.dtype != np.uint8 or img.ndim not in (2, 3):
        raise InputError(path, "<image>", "uint8 [H, W] or [H, W, 3]",
                         f"{img.dtype} {tuple(img.shape)}")
    Image.fromarray(np.ascontiguousarray(img)).save(
        path, format="PNG", optimize=False, compress_level=6)


def _write_json(path: Path, obj: object) -> None:
    path.write_text(json.dumps(obj, sort_keys=True, indent=1, default=_json_default) + "\n")


def _json_default(o: object) -> object:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def _intrinsics_5x5(cams: Cameras, i: int) -> np.ndarray:
    m = np.zeros((5, 5))
    m[:3, :3] = K_to_file(cams.K[i].numpy())
    m[3, 3] = 1.0
    m[4] = cams.dist[i].numpy()
    return m


def _fill_split(split: SplitData, out: Path) -> None:
    cams, names = split.cameras, split.cameras.names
    for sub in ("intrinsics", "pose"):
        (out / sub).mkdir(parents=True)
    for i, name in enumerate(names):
        write_matrix(out / "intrinsics" / f"{name}.txt", _intrinsics_5x5(cams, i))
        write_matrix(out / "pose" / f"{name}.txt", cams.c2w[i].numpy())
    _write_json(out / "camdict.json", cameras_to_camdict(cams, ".png"))
    if split.events is not None:
        if len(split.events) != len(names):
            raise InputError(out, "events", f"one stream per view ({len(names)})",
                             len(split.events))
        (out / "events").mkdir()
        for name, ev in zip(names, split.events):
            _write_events(out / "events" / f"{name}.npz", ev)
    frames = np.asarray(split.frames)
    if frames.size:
        if len(split.frame_times) != frames.shape[0] or frames.shape[1] != len(names):
            raise InputError(out, "frames", f"[F={len(split.frame_times)}, V={len(names)}, ...]",
                             tuple(frames.shape))
        folders = [frame_folder(t) for t in split.frame_times]
        if len(set(folders)) != len(folders):
            raise InputError(out, "frame_times", "distinct whole time units", folders)
        for k, folder in enumerate(folders):
            (out / "rgb" / folder).mkdir(parents=True)
            for i, name in enumerate(names):
                _write_png(out / "rgb" / folder / f"{name}.png", frames[k, i])
    if split.background is not None:
        (out / "background").mkdir()
        for i, name in enumerate(names):
            _write_png(out / "background" / f"{name}.png", split.background[i])
    if split.masks is not None:
        for k, t in enumerate(split.frame_times):
            (out / "mask" / frame_folder(t)).mkdir(parents=True)
            for i, name in enumerate(names):
                _write_png(out / "mask" / frame_folder(t) / f"{name}.png",
                           (np.asarray(split.masks[k, i]) > 0).astype(np.uint8) * 255)


def _write_events(path: Path, ev: EventStream) -> None:
    write_npz(path, x=ev.x.astype(np.int16), y=ev.y.astype(np.int16),
              t=ev.t.astype(np.float64), p=ev.p.astype(np.int8))


def _atomic(target: Path, fill, overwrite: bool) -> Path:
    """Run ``fill(tmp)`` in a temporary folder beside ``target``, then rename it."""
    target = Path(target)
    if target.exists() and not overwrite:
        raise InputError(target, "<folder>", "a path that does not exist yet", "exists")
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=target.parent))
    try:
        fill(tmp)
        os.chmod(tmp, 0o755)
        if target.exists():
            trash = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=target.parent))
            os.replace(target, trash / "old")
            os.replace(tmp, target)
            shutil.rmtree(trash, ignore_errors=True)
        else:
            os.replace(tmp, target)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return target


def write_split(split: SplitData, path: str | Path, overwrite: bool = False) -> Path:
    """Write one split folder (atomically). Returns ``path``."""
    return _atomic(Path(path), lambda tmp: _fill_split(split, tmp), overwrite)


def write_dataset(ds: Dataset, root: str | Path, overwrite: bool = False) -> Path:
    """Write every split of ``ds`` under ``root/<split>/`` plus ``root/meta.json``,
    atomically (the whole scene appears at once). Returns ``root``."""
    def fill(tmp: Path) -> None:
        for name, split in ds.splits.items():
            _fill_split(split, tmp / name)
        _write_json(tmp / "meta.json", ds.meta)
    return _atomic(Path(root), fill, overwrite)
