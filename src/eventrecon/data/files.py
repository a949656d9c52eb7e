"""Parsers and validators for the single files of the published dataset layout.

Each reader takes one path and returns plain NumPy arrays, or raises
:class:`eventrecon.common.errors.InputError` with one line naming the file, the field and
the expectation -- a malformed file never surfaces as a traceback from deep inside
NumPy, zipfile or PIL.

Files handled (docs/method.md, "Data layout of the published dataset"):

- ``intrinsics/<view>.txt``: 5×5 (``K`` top-left 3×3, last row ``k1 k2 p1 p2 k3``),
  5×4 (last row ``k1 k2 p1 p2``), 4×4 or 3×3 (no distortion) -> :func:`read_intrinsics`;
- ``pose/<view>.txt``: 4×4 rigid camera-to-world -> :func:`read_pose`;
- ``events/<view>.npz``: ``x, y, t, p`` -> :func:`read_events_npz`;
- PNG frames, backgrounds, masks -> :func:`read_png`;
- JSON (``camdict.json``, ``meta.json``) -> :func:`read_json`.
"""

from __future__ import annotations

import json
import zipfile
import zlib
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from eventrecon import TIME_SPAN
from eventrecon.common.errors import InputError
from eventrecon.events.stream import EventStream
from eventrecon.render.cameras import RIGID_TOL, K_from_file, check_intrinsics, check_rigid

__all__ = [
    "read_matrix_txt",
    "read_intrinsics",
    "read_pose",
    "check_rigid",
    "RIGID_TOL",
    "read_events_npz",
    "validate_events",
    "read_png",
    "read_json",
]

_NPZ_ERRORS = (zipfile.BadZipFile, zlib.error, OSError, EOFError, ValueError, KeyError)


def read_matrix_txt(path: Path, field: str = "<matrix>") -> np.ndarray:
    """A whitespace-separated numeric matrix ``[R, C]`` (float64) from a text file."""
    try:
        with open(path, "rb") as fh:
            m = np.loadtxt(fh, dtype=np.float64, ndmin=2)
    except FileNotFoundError:
        raise InputError(path, "<file>", "an existing file", "missing") from None
    except (ValueError, UnicodeDecodeError) as e:
        raise InputError(path, field, "rows of numbers with equal length",
                         str(e).splitlines()[0][:80]) from None
    if not np.isfinite(m).all():
        raise InputError(path, field, "finite numbers", "NaN or inf")
    return m


def read_intrinsics(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Intrinsics ``K [3, 3]`` and distortion ``dist [5]`` from one ``intrinsics/*.txt``.

    Accepted shapes: 5×5 (``K`` top-left, last row ``k1 k2 p1 p2 k3``), 5×4 (last row
    ``k1 k2 p1 p2``, ``k3 = 0``), 4×4 and 3×3 (``K`` top-left, no distortion).
    ``K`` must be ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` with ``fx, fy > 0``; it is
    returned in our pixel convention (:func:`eventrecon.render.cameras.K_from_file`).
    """
    m = read_matrix_txt(path, "intrinsics")
    if m.shape not in ((5, 5), (5, 4), (4, 4), (3, 3)):
        raise InputError(path, "intrinsics", "a 5×5, 5×4, 4×4 or 3×3 matrix",
                         "×".join(map(str, m.shape)))
    K = m[:3, :3].copy()
    dist = np.zeros(5, np.float64)
    if m.shape[0] == 5:
        row = m[4]
        dist[: min(5, row.size)] = row[:5]
    check_intrinsics(K, path, "K")
    return K_from_file(K), dist


def read_pose(path: Path, tol: float = RIGID_TOL) -> np.ndarray:
    """A rigid 4×4 camera-to-world matrix (OpenCV axes) from ``pose/*.txt``."""
    m = read_matrix_txt(path, "pose")
    check_rigid(m, path, "pose", tol)
    return m


def _as_int_coords(a: np.ndarray, path: Path, key: str) -> np.ndarray:
    """Integer pixel coordinates; floats are accepted only when integral."""
    if np.issubdtype(a.dtype, np.integer):
        return a
    if np.issubdtype(a.dtype, np.floating):
        if a.size and not (np.isfinite(a).all() and np.array_equal(a, np.round(a))):
            raise InputError(path, key, "integer pixel coordinates",
                             f"{a.dtype} with fractional or non-finite values")
        return a
    raise InputError(path, key, "an integer array", str(a.dtype))


def validate_events(x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray,
                    path: Path | str, width: int | None, height: int | None,
                    binary_polarity: bool = False,
                    t_range: tuple[float, float] | None = (0.0, TIME_SPAN)) -> EventStream:
    """Validate four event arrays and return a compact, time-sorted :class:`EventStream`.

    Checks (all vectorised): 1-D arrays of equal length; integral ``x, y`` inside
    ``[0, W) × [0, H)``; finite, non-decreasing ``t`` inside ``t_range``; ``p ∈ {−1, +1}``
    (or ``{0, 1}`` mapped to ``2p − 1`` when ``binary_polarity``).
    Unsorted timestamps are an error (a silent re-sort would hide a broken converter).
    """
    path = Path(path)
    arrays = {"x": np.asarray(x), "y": np.asarray(y), "t": np.asarray(t), "p": np.asarray(p)}
    n = arrays["t"].shape[0] if arrays["t"].ndim == 1 else -1
    for key, a in arrays.items():
        if a.ndim != 1 or a.shape[0] != n:
            raise InputError(path, key, f"a 1-D array of the same length as t ({n})",
                             f"shape {a.shape}")
    xs = _as_int_coords(arrays["x"], path, "x")
    ys = _as_int_coords(arrays["y"], path, "y")
    for key, a, size in (("x", xs, width), ("y", ys, height)):
        if size is not None and a.size and (a.min() < 0 or a.max() >= size):
            bad = int(np.flatnonzero((a < 0) | (a >= size))[0])
            raise InputError(path, key, f"values in [0, {size - 1}] (inside the image)",
                             f"{a[bad]} at index {bad}")
    t = arrays["t"]
    if not (np.issubdtype(t.dtype, np.floating) or np.issubdtype(t.dtype, np.integer)):
        raise InputError(path, "t", "a numeric array", str(t.dtype))
    t = t.astype(np.float64, copy=False)
    if n and not np.isfinite(t).all():
        bad = int(np.flatnonzero(~np.isfinite(t))[0])
        raise InputError(path, "t", "finite timestamps", f"{t[bad]} at index {bad}")
    if n > 1:
        dec = np.flatnonzero(np.diff(t) < 0)
        if dec.size:
            i = int(dec[0])
            raise InputError(path, "t", "non-decreasing (time-sorted) timestamps",
                             f"t[{i}] = {t[i]} > t[{i + 1}] = {t[i + 1]}")
    if t_range is not None and n and (t[0] < t_range[0] or t[-1] > t_range[1]):
        raise InputError(path, "t", f"times in [{t_range[0]:g}, {t_range[1]:g}]",
                         f"[{t[0]:g}, {t[-1]:g}]")
    p = arrays["p"]
    if not (np.issubdtype(p.dtype, np.integer) or np.issubdtype(p.dtype, np.floating)
            or p.dtype == np.bool_):
        raise InputError(path, "p", "a numeric polarity array", str(p.dtype))
    allowed = (0, 1) if binary_polarity else (-1, 1)
    ok = (p == allowed[0]) | (p == allowed[1])
    if not ok.all():
        bad = np.unique(p[~ok])[:5]
        hint = ""
        if not binary_polarity and np.isin(p, (0, 1)).all():
            hint = " (polarities stored as {0, 1}: pass binary_polarity=True)"
        raise InputError(path, "p", f"values in {{{allowed[0]:+d}, {allowed[1]:+d}}}{hint}",
                         ", ".join(str(v) for v in bad.tolist()))
    p8 = p.astype(np.int8)
    if binary_polarity:
        p8 = 2 * p8 - 1
    return EventStream(xs.astype(np.int16), ys.astype(np.int16), t, p8.astype(np.int8))


def read_events_npz(path: Path, width: int | None, height: int | None,
                    binary_polarity: bool = False,
                    t_range: tuple[float, float] | None = (0.0, TIME_SPAN),
                    keys: tuple[str, str, str, str] = ("x", "y", "t", "p")) -> EventStream:
    """Read and validate ``events/<view>.npz`` (arrays ``x, y, t, p``).

    ``np.load`` reads each array in one call (no Python loop over events); pickled
    objects are refused. See :func:`validate_events` for the checks.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "<file>", "an existing .npz file", "missing")
    try:
        with np.load(path, allow_pickle=False) as z:
            if not hasattr(z, "files"):
                raise InputError(path, "<file>", "an .npz archive of arrays x, y, t, p",
                                 "a single .npy array")
            missing = [k for k in keys if k not in z.files]
            if missing:
                raise InputError(path, missing[0], "arrays " + ", ".join(keys),
                                 "keys " + (", ".join(z.files) or "none"))
            arrays = [z[k] for k in keys]
    except InputError:
        raise
    except _NPZ_ERRORS as e:
        raise InputError(path, "<file>", "a readable .npz archive",
                         f"{type(e).__name__}: {str(e)[:60]}") from None
    return validate_events(*arrays, path=path, width=width, height=height,
                           binary_polarity=binary_polarity, t_range=t_range)


def read_png(path: Path, field: str = "<image>") -> np.ndarray:
    """An 8-bit image: ``[H, W, 3]`` uint8 for colour, ``[H, W]`` for single-channel.

    Palette images are expanded to RGB, alpha channels are dropped; 16-bit or float
    images are refused (the layout stores 8-bit sRGB-encoded frames).
    """
    path = Path(path)
    try:
        with Image.open(path) as im:
            im.load()
            mode = im.mode
            if mode == "P":
                im, mode = im.convert("RGBA"), "RGBA"
            if mode in ("RGBA", "RGBX", "CMYK", "YCbCr"):
                im, mode = im.convert("RGB"), "RGB"
            elif mode == "LA":
                im, mode = im.convert("L"), "L"
            elif mode == "1":
                im, mode = im.convert("L"), "L"
            if mode not in ("RGB", "L"):
                raise InputError(path, field, "an 8-bit RGB or greyscale PNG", f"mode {mode}")
            arr = np.asarray(im, dtype=np.uint8).copy()
    except FileNotFoundError:
        raise InputError(path, "<file>", "an existing PNG file", "missing") from None
    except InputError:
        raise
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError, zlib.error) as e:
        raise InputError(path, "<file>", "a readable PNG image",
                         f"{type(e).__name__}: {str(e)[:60]}") from None
    return arr


def read_json(path: Path) -> object:
    """Parse a JSON file (clear error on a missing file or a syntax error)."""
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(path, "<file>", "an existing JSON file", "missing") from None
    except UnicodeDecodeError:
        raise InputError(path, "<json>", "UTF-8 text", "binary data") from None
    except json.JSONDecodeError as e:
        raise InputError(path, "<json>", "valid JSON",
                         f"{e.msg} at line {e.lineno} column {e.colno}") from None
