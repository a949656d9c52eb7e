"""AEDAT4 → published layout, round trip through files written by dv-processing.

dv-processing (iniVation's own library) writes the recordings, the project decodes them
with the ``aedat`` package, so the two sides share no code.
"""

from __future__ import annotations

import json
from pathlib import Path

import dv_processing as dv  # a test dependency ([test] extra): a missing one fails, never skips
import numpy as np
import pytest

from eventrecon.common.errors import InputError
from eventrecon.convert import main
from eventrecon.data.layout import read_split
from eventrecon.data.recordings import convert_aedat4
from eventrecon.render.cameras import cameras_to_camdict, ring_rig

W, H = 40, 30
T0 = 1_700_000_000_000_000  # µs, a wall-clock-like shared timestamp
FRAME_DT = 33_333  # µs, ~30 fps APS frames


#: External sync pulses every camera receives (µs after T0): rising and falling edges.
PULSES = (200_000, 200_500, 900_000, 900_500, 1_600_000, 1_600_500)


def write_camera(path: Path, rng: np.random.Generator, offset_us: int, duration_us: int,
                 grey: bool = False, trigger_skew_us: int = 0) -> dict:
    """One camera: random events over [T0+offset, T0+offset+duration], frames every 33 ms,
    the external pulses of :data:`PULSES` (shifted by ``trigger_skew_us``) as triggers."""
    cfg = dv.io.MonoCameraWriter.DAVISConfig(f"DAVIS346_{path.stem}", (W, H))
    writer = dv.io.MonoCameraWriter(str(path), cfg)
    n = 4000
    t = np.sort(rng.integers(T0 + offset_us, T0 + offset_us + duration_us, n))
    t[0], t[-1] = T0 + offset_us, T0 + offset_us + duration_us
    x, y = rng.integers(0, W, n), rng.integers(0, H, n)
    on = rng.random(n) < 0.5
    store = dv.EventStore()
    for i in range(n):
        store.push_back(int(t[i]), int(x[i]), int(y[i]), bool(on[i]))
    frames, frame_t = [], []
    ft = T0 + offset_us + 1000
    k = 0
    while ft < T0 + offset_us + duration_us:
        img = rng.integers(0, 256, (H, W) if grey else (H, W, 3), dtype=np.uint8)
        # dv-processing frames are OpenCV BGR; the file stores RGB
        writer.writeFrame(dv.Frame(int(ft), img if grey else np.ascontiguousarray(img[..., ::-1])))
        frames.append(img)
        frame_t.append(ft)
        ft += FRAME_DT + int(rng.integers(-200, 200))
        k += 1
    writer.writeEvents(store)
    triggers = dv.TriggerPacket()
    kinds = (dv.TriggerType.EXTERNAL_SIGNAL_RISING_EDGE,
             dv.TriggerType.EXTERNAL_SIGNAL_FALLING_EDGE)
    trig_t = [T0 + p + trigger_skew_us for p in PULSES]
    for k, tt in enumerate(trig_t):
        triggers.elements.append(dv.Trigger(int(tt), kinds[k % 2]))
    writer.writeTriggerPacket(triggers)
    del writer  # flushes and closes the file
    return dict(t=t, x=x, y=y, on=on, frames=frames, frame_t=np.array(frame_t),
                trig_t=np.array(trig_t, np.int64), trig_source=[1, 2] * (len(PULSES) // 2))


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    root = tmp_path_factory.mktemp("aedat")
    rng = np.random.default_rng(0)
    offsets = [0, 150_000, 40_000]  # cameras started at different times on one clock
    cams = [write_camera(root / f"cam{i}.aedat4", rng, off, 2_000_000 - off)
            for i, off in enumerate(offsets)]
    rig_cams = ring_rig(3, W, H, dist=(-0.4, 0.2, 0, 0, 0))
    (root / "camdict.json").write_text(json.dumps(cameras_to_camdict(rig_cams)))
    return root, cams


def test_round_trip(rig):
    root, cams = rig
    out = convert_aedat4([root / f"cam{i}.aedat4" for i in range(3)], root / "scene",
                         start_us=100_000, end_us=1_100_000, fps=5, background_us=0,
                         camdict=root / "camdict.json")
    s0 = T0 + 150_000  # shared span starts with the latest camera
    start, end = s0 + 100_000, s0 + 1_100_000
    sp = read_split(out / "train")
    assert sp.n_views == 3 and (sp.cameras.width, sp.cameras.height) == (W, H)
    np.testing.assert_array_equal(sp.frame_times, [0, 200, 400, 600, 800, 1000])
    targets = start + np.arange(6) * 200_000
    for v, cam in enumerate(cams):
        keep = (cam["t"] >= start) & (cam["t"] <= end)
        ev = sp.events[v]
        np.testing.assert_array_equal(ev.x, cam["x"][keep])
        np.testing.assert_array_equal(ev.y, cam["y"][keep])
        np.testing.assert_array_equal(ev.p, np.where(cam["on"][keep], 1, -1))
        np.testing.assert_allclose(ev.t, (cam["t"][keep] - start) * 1e-3, rtol=0, atol=1e-9)
        # the APS frame nearest each target time, pixel for pixel
        for k, tgt in enumerate(targets):
            j = int(np.argmin(np.abs(cam["frame_t"] - tgt)))
            np.testing.assert_array_equal(sp.frames[k, v], cam["frames"][j])
        jb = int(np.argmin(np.abs(cam["frame_t"] - s0)))
        np.testing.assert_array_equal(sp.background[v], cam["frames"][jb])
    meta = json.loads((out / "meta.json").read_text())
    assert (meta["start_us"], meta["end_us"], meta["duration_s"]) == (start, end, 1.0)
    assert meta["tonemap_eps"] == 3e-2 and meta["decay"] == 0.93 and meta["bayer"] is True
    assert len(meta["segments"]) == 5 and meta["segments"][0] == [0.0, 210.0]
    # the triggers inside the cut, exactly: µs, normalised time, source
    for v, cam in enumerate(cams):
        keep = (cam["trig_t"] >= start) & (cam["trig_t"] <= end)
        trig = meta["triggers"][f"{v:02d}"]
        assert trig["t_us"] == cam["trig_t"][keep].tolist()
        assert trig["source"] == np.array(cam["trig_source"])[keep].tolist()
        np.testing.assert_allclose(trig["t"], (cam["trig_t"][keep] - start) * 1e-3, atol=1e-9)
    assert meta["triggers"]["00"]["t_us"] == [T0 + 900_000, T0 + 900_500]


def test_default_span_and_cli(rig, tmp_path):
    root, cams = rig
    rc = main(["aedat4", "--inputs", *[str(root / f"cam{i}.aedat4") for i in range(3)],
               "--out", str(tmp_path / "scene"), "--fps", "2", "--camdict",
               str(root / "camdict.json")])
    assert rc == 0
    sp = read_split(tmp_path / "scene" / "train")
    s0, s1 = T0 + 150_000, T0 + 2_000_000  # [latest first event, earliest last event]
    for v, cam in enumerate(cams):
        keep = (cam["t"] >= s0) & (cam["t"] <= s1)
        assert len(sp.events[v]) == int(keep.sum())
        assert sp.events[v].t[0] >= 0 and sp.events[v].t[-1] <= 1000.0
    assert sp.events[1].t[0] == 0.0 and sp.events[0].t[-1] == 1000.0
    np.testing.assert_allclose(sp.frame_times, [0, 500 / 1.85, 1000 / 1.85, 1500 / 1.85],
                               atol=1e-3)


def test_greyscale_frames_become_bayer_raw(tmp_path):
    rng = np.random.default_rng(1)
    cam = write_camera(tmp_path / "g.aedat4", rng, 0, 500_000, grey=True)
    out = convert_aedat4([tmp_path / "g.aedat4"], tmp_path / "scene", fps=4)
    import imageio.v3 as iio
    img = iio.imread(out / "train" / "rgb" / "0500" / "00.png")
    j = int(np.argmin(np.abs(cam["frame_t"] - (T0 + 250_000))))
    assert img.shape == (H, W)
    np.testing.assert_array_equal(img, cam["frames"][j])


def test_unsynchronised_cameras_are_caught_by_their_triggers(tmp_path, rig):
    root, _ = rig
    rng = np.random.default_rng(3)
    write_camera(tmp_path / "skewed.aedat4", rng, 0, 2_000_000, trigger_skew_us=800)
    with pytest.raises(InputError, match=r"skewed\.aedat4: triggers: expected external trigger 0 "
                                         r"at the time of cam0\.aedat4's \(±100 µs.*got "
                                         rf"{T0 + 200_800} vs {T0 + 200_000} µs"):
        convert_aedat4([root / "cam0.aedat4", tmp_path / "skewed.aedat4"], tmp_path / "o")
    # within a looser tolerance the same files convert
    out = convert_aedat4([root / "cam0.aedat4", tmp_path / "skewed.aedat4"], tmp_path / "o",
                         sync_tolerance_us=1000)
    assert (out / "train" / "events" / "01.npz").is_file()


def test_bad_recordings(tmp_path, rig):
    root, _ = rig
    (tmp_path / "bad.aedat4").write_bytes(b"#!AER-DAT4.0\r\n" + b"\0" * 64)
    with pytest.raises(InputError, match=r"bad\.aedat4: <file>: expected a readable AEDAT4"):
        convert_aedat4([tmp_path / "bad.aedat4"], tmp_path / "o1")
    data = (root / "cam0.aedat4").read_bytes()
    (tmp_path / "cut.aedat4").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match=r"cut\.aedat4: <file>: expected a (complete|readable)"):
        convert_aedat4([tmp_path / "cut.aedat4"], tmp_path / "o2")
    rng = np.random.default_rng(2)
    write_camera(tmp_path / "late.aedat4", rng, 3_000_000, 500_000)  # after cam0 ended
    with pytest.raises(InputError, match=r"time span: expected recordings that overlap"):
        convert_aedat4([root / "cam0.aedat4", tmp_path / "late.aedat4"], tmp_path / "o3")
    with pytest.raises(InputError, match=r"cut: expected 0 ≤ start < end"):
        convert_aedat4([root / "cam0.aedat4"], tmp_path / "o4", start_us=5_000_000)
    assert not any(p.name.startswith(".o") for p in tmp_path.iterdir())  # no temp folders left
