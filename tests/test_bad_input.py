"""Bad dataset files: each gives one InputError line naming the file and the field.

Every case starts from a valid split written by the independent writer of
``test_layout.py``, breaks one thing, and checks the message (file + field regex), that
it is a single line, and that it is an :class:`InputError` (not a NumPy/zip/PIL error).
"""

from __future__ import annotations

import json
import re
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from test_layout import write_split

from eventrecon.common.errors import InputError
from eventrecon.data.layout import read_dataset, read_split


def _npz(path: Path, **changes) -> None:
    """Rewrite ``path`` with some arrays replaced (``None`` drops a key)."""
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    for k, v in changes.items():
        if v is None:
            arrays.pop(k)
        else:
            arrays[k] = v
    np.savez(path, **arrays)


def _ev(s: Path) -> Path:
    return s / "events" / "01.npz"


def _unsorted(s: Path) -> None:
    with np.load(_ev(s)) as z:
        t = z["t"].copy()
    t[10], t[11] = t[11] + 1.0, t[10]
    _npz(_ev(s), t=t)


def _with_nan(s: Path) -> None:
    with np.load(_ev(s)) as z:
        t = z["t"].copy()
    t[5] = np.nan
    _npz(_ev(s), t=t)


def _column(s: Path, key: str, value) -> None:
    with np.load(_ev(s)) as z:
        a = z[key].copy()
    a[3] = value
    _npz(_ev(s), **{key: a})


def _scaled_pose(s: Path) -> None:
    m = np.loadtxt(s / "pose" / "02.txt")
    m[:3, :3] *= 1.1
    np.savetxt(s / "pose" / "02.txt", m)


def _reflected_pose(s: Path) -> None:
    m = np.loadtxt(s / "pose" / "02.txt")
    m[:3, 0] *= -1  # orthonormal but det = −1
    np.savetxt(s / "pose" / "02.txt", m)


def _truncate(path: Path, keep: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def _camdict(s: Path, text: str) -> None:
    (s / "camdict.json").write_text(text)


def _camdict_missing_w2c(s: Path) -> None:
    cd = json.loads((s / "camdict.json").read_text())
    del cd["01.png"]["W2C"]
    _camdict(s, json.dumps(cd))


def _camdict_entry(s: Path, key: str, value) -> None:
    cd = json.loads((s / "camdict.json").read_text())
    cd["01.png"][key] = value
    _camdict(s, json.dumps(cd))


def _camdict_only(s: Path, key: str, value) -> None:
    """Cameras from camdict.json alone (no intrinsics/, pose/), one entry broken."""
    shutil.rmtree(s / "intrinsics")
    shutil.rmtree(s / "pose")
    _camdict_entry(s, key, value)


def _wrong_size_frame(s: Path) -> None:
    import imageio.v3 as iio
    iio.imwrite(s / "rgb" / "0200" / "01.png", np.zeros((21, 30, 3), np.uint8))


def _intrinsics_3x4(s: Path) -> None:
    np.savetxt(s / "intrinsics" / "01.txt", np.eye(3, 4))


#: name -> (break the split, regex the message must match)
CASES: dict[str, tuple[Callable[[Path], None], str]] = {
    "missing pose folder": (
        lambda s: shutil.rmtree(s / "pose"),
        r"pose: <folder>: expected an existing folder"),
    "mismatched view counts": (lambda s: _ev(s).unlink(),
                               r"events: view count: expected 3 views .*got 2"),
    "mismatched view names": (lambda s: _ev(s).rename(s / "events" / "07.npz"),
                              r"events: view names: expected .*'01'.*got '02'"),
    "x out of image": (lambda s: _column(s, "x", 30), r"01\.npz: x: expected values in \[0, 29\]"),
    "y negative": (lambda s: _column(s, "y", -1), r"01\.npz: y: expected values in \[0, 19\]"),
    "unsorted t": (_unsorted, r"01\.npz: t: expected non-decreasing .*got t\[10\]"),
    "NaN t": (_with_nan, r"01\.npz: t: expected finite timestamps, got nan at index 5"),
    "t beyond 1000": (lambda s: _npz(_ev(s), t=np.linspace(0, 1001, 500)),
                      r"01\.npz: t: expected times in \[0, 1000\]"),
    "polarity 0": (lambda s: _column(s, "p", 0),
                   r"01\.npz: p: expected values in \{-1, \+1\}.*got 0"),
    "polarity 2": (lambda s: _column(s, "p", 2), r"01\.npz: p: expected .*got 2"),
    "float x with fractions": (lambda s: _npz(_ev(s), x=np.full(500, 1.5)),
                               r"01\.npz: x: expected integer pixel coordinates, got float64"),
    "length mismatch": (lambda s: _npz(_ev(s), y=np.zeros(499, np.int64)),
                        r"01\.npz: y: expected a 1-D array of the same length as t \(500\)"),
    "missing npz key": (lambda s: _npz(_ev(s), p=None), r"01\.npz: p: expected arrays x, y, t, p"),
    "corrupt npz": (lambda s: _ev(s).write_bytes(b"PK\x03\x04 not really a zip" * 10),
                    r"01\.npz: <file>: expected a readable \.npz archive"),
    "truncated npz": (lambda s: _truncate(_ev(s)), r"01\.npz: <file>: expected a readable \.npz"),
    "non-rigid pose (scale)": (_scaled_pose, r"pose[/\\]02\.txt: pose: .*got a non-rigid pose"),
    "non-rigid pose (reflection)": (_reflected_pose,
                                    r"02\.txt: pose: .*non-rigid pose.*det R = -1"),
    "pose last row": (lambda s: np.savetxt(s / "pose" / "00.txt",
                                           np.vstack([np.eye(4)[:3], [0, 0, 1, 1]])),
                      r"00\.txt: pose: .*non-rigid pose"),
    "pose with text": (lambda s: (s / "pose" / "00.txt").write_text("1 0 0 0\n0 one 0 0\n"),
                       r"00\.txt: pose: expected rows of numbers"),
    "intrinsics wrong shape": (
        _intrinsics_3x4,
        r"intrinsics[/\\]01\.txt: intrinsics: expected a 5×5, 5×4, 4×4.*got 3×4"),
    "intrinsics NaN": (
        lambda s: (s / "intrinsics" / "00.txt").write_text("nan 0 1\n0 1 1\n0 0 1\n"),
        r"00\.txt: intrinsics: expected finite numbers"),
    "intrinsics not a K": (lambda s: np.savetxt(s / "intrinsics" / "00.txt", -np.eye(3)),
                           r"00\.txt: K: expected \[\[fx"),
    "truncated PNG": (lambda s: _truncate(s / "rgb" / "0200" / "02.png", 0.6),
                      r"0200[/\\]02\.png: <file>: expected a readable PNG"),
    "wrong image size among frames": (
        _wrong_size_frame, r"0200[/\\]01\.png: image size: expected H×W = 20×30 .*got 21×30"),
    "frame folder not a time": (lambda s: (s / "rgb" / "0200").rename(s / "rgb" / "mid"),
                                r"mid: frame time: expected a folder named by its time unit"),
    "malformed camdict JSON": (lambda s: _camdict(s, '{"00.png": {"K": [1, 2,'),
                               r"camdict\.json: <json>: expected valid JSON"),
    "camdict missing W2C": (_camdict_missing_w2c, r"camdict\.json: 01\.png\.W2C: expected a value"),
    "camdict wrong type": (lambda s: _camdict(s, json.dumps({"00.png": {"K": "eye", "W2C": [],
                                                                        "img_size": [30, 20]}})),
                           r"camdict\.json: 00\.png\.K/W2C/dist: expected lists of numbers"),
    "camdict K with NaN": (lambda s: _camdict_only(s, "K", [float("nan")] + [0.0] * 15),
                           r"camdict\.json: 01\.png\.K: expected \[\[fx"),
    "camdict negative focal length": (
        lambda s: _camdict_only(s, "K", [-25.0, 0, 14.5, 0, 0, 26.0, 9.5, 0, 0, 0, 1, 0,
                                         0, 0, 0, 1]),
        r"camdict\.json: 01\.png\.K: expected \[\[fx, s, cx\].*fx, fy > 0"),
    "camdict short dist": (lambda s: _camdict_only(s, "dist", [-0.4, 0.2]),
                           r"camdict\.json: 01\.png\.dist: expected 4 or 5 finite numbers"),
    "camdict non-rigid W2C": (lambda s: _camdict_only(s, "W2C", (2.0 * np.eye(4)).ravel().tolist()),
                              r"camdict\.json: 01\.png\.W2C: .*non-rigid pose"),
    "camdict img_size vs PNGs": (
        lambda s: _camdict(s, (s / "camdict.json").read_text().replace("[30, 20]", "[346, 260]")),
        r"camdict\.json: img_size: expected \[30, 20\] as the PNGs"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_split_file(tmp_path, case):
    split = tmp_path / "scene" / "train"
    write_split(split, seed=7, camdict=True)
    breaker, pattern = CASES[case]
    breaker(split)
    with pytest.raises(InputError) as info:
        read_split(split)
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith(str(split)), msg  # names the file by its full path
    assert re.search(pattern, msg), msg


def test_missing_split_folder(tmp_path):
    with pytest.raises(InputError, match=r"nowhere: <folder>: expected an existing split folder"):
        read_split(tmp_path / "nowhere")


def test_malformed_meta_json(tmp_path):
    write_split(tmp_path / "scene" / "train", n_events=5)
    (tmp_path / "scene" / "meta.json").write_text("[1, 2")
    with pytest.raises(InputError, match=r"meta\.json: <json>: expected valid JSON, got .*line 1"):
        read_dataset(tmp_path / "scene")


def test_binary_polarity_only_with_option(tmp_path):
    split = tmp_path / "train"
    truth = write_split(split, n_events=50)
    for v in range(3):
        _npz(split / "events" / f"{v:02d}.npz", p=(truth["events"][v]["p"] > 0).astype(np.uint8))
    hint = r"\(polarities stored as \{0, 1\}: pass binary_polarity=True\)"
    with pytest.raises(InputError, match=r"00\.npz: p: expected values in \{-1, \+1\} " + hint):
        read_split(split)
    sp = read_split(split, binary_polarity=True)
    for v in range(3):
        np.testing.assert_array_equal(sp.events[v].p, truth["events"][v]["p"])
