"""Simulated datasets on disk: reproducible bytes, write → read round trip, caching,
atomic writes, noise rates, the scene library."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from eventrecon.common.errors import InputError
from eventrecon.data.layout import read_dataset
from eventrecon.data.writer import write_dataset
from eventrecon.sim import pipeline
from eventrecon.sim.pipeline import dataset_path, ensure_dataset, simulate_dataset
from eventrecon.sim.spec import parse_spec

CONF = Path(__file__).resolve().parents[1] / "conf" / "scene"


def tiny(**over) -> dict:
    cfg = {
        "name": "tiny", "seed": 11, "width": 20, "height": 16, "duration_s": 1.0,
        "rgb_fps": 3, "eval_fps": 2, "tonemap_eps": 3e-2, "decay": 0.93,
        "segments": [[0, 600], [400, 1000]],
        "rig": {"n_train": 2, "n_heldout": 1},
        "objects": [{"type": "sphere", "radius": 0.2, "position": [0, -0.3, 0],
                     "texture": {"type": "stripes", "colors": [[0.9, 0.3, 0.1], [0.1, 0.3, 0.9]],
                                 "period": 0.1},
                     "motion": [{"type": "orbit", "radius": 0.2}, {"type": "spin"}]}],
        "events": [{"name": "bayer"}, {"name": "threshold_mismatch", "sigma": 0.03},
                   {"name": "shot_noise", "rate_hz": 2.0}, {"name": "refractory",
                                                             "period_s": 1e-3}],
        "frames": [{"name": "exposure_blur", "exposure_s": 0.05, "samples": 4},
                   {"name": "low_light", "photons": 200.0, "read_noise": 0.01},
                   {"name": "crf", "eps": 0.03}, {"name": "quantize_8bit"}],
    }
    cfg.update(over)
    return cfg


def _digest(root: Path) -> dict:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_same_seed_byte_identical_other_seed_differs(tmp_path):
    a = ensure_dataset(tiny(), tmp_path / "a")
    b = ensure_dataset(tiny(), tmp_path / "b")
    da, db = _digest(a), _digest(b)
    assert len(da) > 20 and da == db
    c = ensure_dataset(tiny(seed=12), tmp_path / "c")
    dc = _digest(c)
    assert dc["train/events/00.npz"] != da["train/events/00.npz"]
    assert dc["train/rgb/0000/00.png"] != da["train/rgb/0000/00.png"]


def test_write_read_round_trip_identical_arrays(tmp_path):
    ds = simulate_dataset(tiny())
    root = write_dataset(ds, tmp_path / "scene")
    back = read_dataset(root)
    assert set(back.splits) == {"train", "validation"}
    for name, s in ds.splits.items():
        r = back.splits[name]
        assert r.cameras.names == s.cameras.names
        np.testing.assert_array_equal(r.cameras.K.numpy(), s.cameras.K.numpy())
        np.testing.assert_array_equal(r.cameras.c2w.numpy(), s.cameras.c2w.numpy())
        np.testing.assert_array_equal(r.frame_times, s.frame_times)
        np.testing.assert_array_equal(r.frames, s.frames)
        np.testing.assert_array_equal(r.background, s.background)
        if s.events is None:
            continue
        for e, f in zip(s.events, r.events):
            for k in "xytp":
                assert getattr(f, k).dtype == getattr(e, k).dtype
                np.testing.assert_array_equal(getattr(f, k), getattr(e, k))
    assert back.meta["decay"] == 0.93 and back.meta["bayer"] is True
    assert back.meta["tonemap_eps"] == 3e-2 and back.meta["segments"] == [[0, 600], [400, 1000]]
    assert [e["name"] for e in back.meta["effects"]["events"]][:2] == ["bayer",
                                                                       "threshold_mismatch"]
    tr = ds.splits["train"]
    assert tr.frame_times.tolist() == [0, 333, 667, 1000]
    assert sorted(p.name for p in (root / "train" / "rgb").iterdir()) == \
        ["0000", "0333", "0667", "1000"]
    ev = tr.events[0]
    assert np.all(np.diff(ev.t) >= 0) and ev.t.min() >= 0 and ev.t.max() <= 1000
    assert set(np.unique(ev.p).tolist()) <= {-1, 1}


def test_ensure_dataset_caches_and_crash_leaves_nothing(tmp_path, monkeypatch):
    p = ensure_dataset(tiny(events=[], frames=[]), tmp_path)
    assert p == dataset_path(tiny(events=[], frames=[]), tmp_path)
    assert p.name.startswith("tiny-") and (p / "meta.json").is_file()

    def boom(*a, **k):
        raise RuntimeError("simulation must not run again")
    monkeypatch.setattr(pipeline, "simulate_dataset", boom)
    assert ensure_dataset(tiny(events=[], frames=[]), tmp_path) == p
    # a different config is simulated; a crash during writing leaves no folder behind
    monkeypatch.undo()
    import eventrecon.data.writer as writer

    def crash(split, out):
        (out / "partial").mkdir(parents=True)
        raise KeyboardInterrupt
    monkeypatch.setattr(writer, "_fill_split", crash)
    with pytest.raises(KeyboardInterrupt):
        ensure_dataset(tiny(seed=5, events=[], frames=[]), tmp_path)
    assert sorted(x.name for x in tmp_path.iterdir() if x.name != pipeline.LOCKS) == [p.name]


def test_static_plus_shot_noise_rate_within_5_percent():
    """conf/scene/static.yaml (nothing moves) plus shot noise at r Hz: the measured rate is
    r within 5 % (about 12 k events: the Poisson standard error is ~1 %)."""
    cfg = OmegaConf.load(CONF / "static.yaml")
    cfg.width, cfg.height, cfg.rig.n_train, cfg.rig.n_heldout = 32, 24, 2, 0
    cfg.events = [{"name": "shot_noise", "rate_hz": 4.0}]
    ds = simulate_dataset(cfg)
    n = sum(len(e) for e in ds.splits["train"].events)
    pixel_seconds = 2 * 32 * 24 * float(cfg.duration_s)
    assert n / pixel_seconds == pytest.approx(4.0, rel=0.05)


def test_unlisted_effects_run_nothing_and_draw_no_random_numbers(monkeypatch):
    """Simulate a scene listing one event and one frame effect: only those two are
    configured, applied and given a random stream; the global NumPy and torch random
    states are not touched."""
    import torch

    from eventrecon.sim import event_sim, frames
    from eventrecon.sim.event_effects import EVENT_EFFECTS
    from eventrecon.sim.frame_effects import FRAME_EFFECTS

    drawn, called = [], []

    def spy_rng(fn):
        def wrapped(seed, side, name, *ids):
            drawn.append((side, name))
            return fn(seed, side, name, *ids)
        return wrapped

    monkeypatch.setattr(event_sim, "effect_rng", spy_rng(event_sim.effect_rng))
    monkeypatch.setattr(frames, "effect_rng", spy_rng(frames.effect_rng))
    def spy_method(original, method: str):
        def spy(self, *a, **k):
            called.append((self.name, method))
            return original(self, *a, **k)
        return spy

    for registry in (EVENT_EFFECTS, FRAME_EFFECTS):
        for cls in registry.classes.values():
            for method in ("apply", "configure"):
                if method in vars(cls):
                    monkeypatch.setattr(cls, method, spy_method(vars(cls)[method], method))
    np_state, torch_state = np.random.get_state()[1].copy(), torch.random.get_rng_state()
    simulate_dataset(tiny(events=[{"name": "shot_noise", "rate_hz": 2.0}],
                          frames=[{"name": "crf", "eps": 0.03}]))
    assert {name for _, name in drawn} == {"shot_noise", "crf"}
    assert {name for name, _ in called} == {"shot_noise", "crf"}
    np.testing.assert_array_equal(np.random.get_state()[1], np_state)
    assert torch.equal(torch.random.get_rng_state(), torch_state)


@pytest.mark.parametrize("name", ["spheres", "blocks", "rig_lowlight", "static", "lego", "dress",
                                  "blender", "static_lego"])
def test_scene_library_parses_and_stays_in_cylinder(name):
    cfg = OmegaConf.load(CONF / f"{name}.yaml")
    assert (CONF / f"{name}.yaml").read_text().startswith("# python ")
    spec = parse_spec(cfg)
    assert spec.scene.cylinder_violation(**spec.cylinder) == 0.0
    if name == "static":
        assert not spec.scene.moving and spec.event_effects == []
    if name == "rig_lowlight":
        assert spec.bayer and spec.decay == 0.93 and spec.tonemap_eps == 3e-2
        assert len(spec.segments) == 5 and spec.rgb_fps == 5


def test_static_library_scene_zero_events_at_small_size():
    cfg = OmegaConf.load(CONF / "static.yaml")
    cfg.width, cfg.height, cfg.rig.n_train = 24, 18, 2
    ds = simulate_dataset(cfg)
    assert sum(len(e) for e in ds.splits["train"].events) == 0
    assert ds.meta["sim"]["pixel_samples"] == 0
    # its objects are the subject: the background images are the empty stage (the
    # background colour alone), so an empty field cannot score the frames
    held = ds.splits["validation"]
    assert np.all(held.background == np.round(255 * 0.353 ** (1 / 2.2)))
    assert (held.frames[0, 0] != held.background[0]).any(-1).mean() > 0.03


def test_static_objects_are_background_unless_marked_subject():
    from eventrecon.sim.scene import parse_object

    box = {"type": "box", "size": [0.2, 0.2, 0.2],
           "texture": {"type": "solid", "color": [0.5, 0.5, 0.5]}}
    assert parse_object(box, "s", "objects[0].").in_background  # a static prop
    assert not parse_object({**box, "subject": True}, "s", "objects[0].").in_background
    spin = {**box, "motion": {"type": "spin", "axis": [0, 1, 0], "turns": 1}}
    assert not parse_object(spin, "s", "objects[0].").in_background  # moving: never
    with pytest.raises(InputError, match=r"objects\[0\]\.subject: expected a bool"):
        parse_object({**box, "subject": "yes"}, "s", "objects[0].")


def test_parallel_callers_simulate_once_and_both_get_the_dataset(tmp_path: Path):
    """Two processes (a joblib sweep) asking for the same missing scene at the same time:
    one simulates, the other waits on the lock and reuses it; both see the same folder."""
    import json
    import subprocess
    import sys

    cfg = json.dumps(tiny(name="race", events=[], frames=[]))
    code = ("import json, logging, sys\n"
            "logging.basicConfig(level=logging.INFO, format='%(name)s %(message)s')\n"
            "from eventrecon.sim.pipeline import ensure_dataset\n"
            f"print(ensure_dataset(json.loads({cfg!r}), {str(tmp_path)!r}))\n")
    import fcntl
    import time

    lock = tmp_path / pipeline.LOCKS / f"{dataset_path(json.loads(cfg), tmp_path).name}.lock"
    lock.parent.mkdir(parents=True)
    with open(lock, "a") as held:  # hold the lock so that both callers queue on it
        fcntl.flock(held.fileno(), fcntl.LOCK_EX)
        procs = [subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True) for _ in range(2)]
        time.sleep(4.0)  # both have imported and found no dataset by now
        assert all(p.poll() is None for p in procs)  # ...and wait on the lock
        fcntl.flock(held.fileno(), fcntl.LOCK_UN)
    outs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [e[-2000:] for _, e in outs]
    assert outs[0][0] == outs[1][0]  # the same dataset path
    logs = "".join(e for _, e in outs)
    assert logs.count("simulated race") == 1, logs[-3000:]
    assert (Path(outs[0][0].strip()) / "meta.json").is_file()


def test_a_real_rigs_camdict_drives_the_simulator(tmp_path: Path):
    """``rig.camdict``: the simulator renders what that rig (346x260, k1 ~ -0.4) would see."""
    import json
    import shutil

    from eventrecon.render.cameras import load_camdict

    camdict = tmp_path / "rig_camdict.json"
    shutil.copy(Path(__file__).parent / "data" / "rig_camdict.json", camdict)
    rig = load_camdict(camdict)
    cfg = tiny(name="rigcams", width=346, height=260, rig={"camdict": str(camdict),
                                                           "n_heldout": 1},
               events=[], frames=[])
    cfg["objects"][0]["motion"] = {"type": "linear", "to": [0.2, -0.3, 0.0]}
    path = ensure_dataset(cfg, tmp_path / "data")
    ds = read_dataset(path)
    train, held = ds.splits["train"], ds.splits["validation"]
    assert (train.n_views, held.n_views) == (len(rig) - 1, 1)
    for split, idx in ((train, range(len(rig) - 1)), (held, [len(rig) - 1])):
        cams = split.cameras
        assert (cams.width, cams.height) == (346, 260)
        np.testing.assert_allclose(cams.K.numpy(), rig.K[list(idx)].numpy(), rtol=1e-12)
        np.testing.assert_allclose(cams.dist.numpy(), rig.dist[list(idx)].numpy(), rtol=1e-12)
        np.testing.assert_allclose(cams.c2w.numpy(), rig.c2w[list(idx)].numpy(), atol=1e-12)
    assert all(len(e) > 100 for e in train.events)  # the moving sphere makes events in every view
    for e in train.events:
        assert 0 <= e.x.min() and e.x.max() < 346 and 0 <= e.y.min() and e.y.max() < 260
    # an edited calibration is a new dataset, not the cached one
    data = json.loads(camdict.read_text())
    data["00.png"]["K"][0] *= 1.01
    camdict.write_text(json.dumps(data))
    assert dataset_path(cfg, tmp_path / "data") != path
    # a scene size that is not the camdict's is one clear line
    with pytest.raises(InputError, match=r"width/height: expected the image size of rig\.camdict"):
        simulate_dataset(tiny(rig={"camdict": str(camdict)}), tmp_path / "x")


def _mask_scene() -> dict:
    """Spheres with known centres over time, a floor, a static prop, a static subject and
    a sphere carried by a spinning group; frames blurred over their exposure."""
    return tiny(
        name="masks", width=32, height=24, events=[],
        frames=[{"name": "exposure_blur", "exposure_s": 0.2, "samples": 3}],
        objects=[
            {"type": "plane", "height": 0.3,
             "texture": {"type": "solid", "color": [0.3, 0.3, 0.3]}},
            {"type": "sphere", "radius": 0.12, "position": [0, -0.3, 0],        # moving
             "motion": {"type": "orbit", "radius": 0.15, "turns": 1.0}},
            {"type": "sphere", "radius": 0.08, "position": [0.25, -0.2, 0.1],   # static subject
             "subject": True},
            {"type": "sphere", "radius": 0.1, "position": [-0.25, -0.05, -0.2]},  # static prop
            {"type": "group", "name": "arm", "position": [-0.2, -0.1, 0],
             "motion": {"type": "spin", "axis": [0, 1, 0], "turns": 1.0}},
            {"type": "sphere", "parent": "arm", "radius": 0.06, "position": [0.1, 0, 0]},
        ])


def _independent_masks(cams, times: np.ndarray) -> np.ndarray:
    """``[F, V, H, W]``: whether each pixel's centre ray first hits the moving sphere, the
    subject or the group's sphere -- analytic centres, pinhole rays from ``K`` and
    ``c2w``, the floor as ``y = 0.3``; no simulator code."""
    H, W = cams.height, cams.width
    v, u = np.mgrid[0:H, 0:W]
    out = []
    for tu in times:
        t = tu / 1000.0
        ph = 2 * np.pi * t
        spheres = [(np.array([0.15 * np.sin(ph), -0.3, 0.15 * np.cos(ph)]), 0.12, True),
                   (np.array([0.25, -0.2, 0.1]), 0.08, True),
                   (np.array([-0.25, -0.05, -0.2]), 0.1, False),
                   (np.array([-0.2 + 0.1 * np.cos(ph), -0.1, -0.1 * np.sin(ph)]), 0.06, True)]
        row = []
        for k in range(len(cams)):
            K, c2w = cams.K[k].numpy(), cams.c2w[k].numpy()
            dc = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
            d = dc @ c2w[:3, :3].T
            d /= np.linalg.norm(d, axis=-1, keepdims=True)
            o = c2w[:3, 3]
            best = np.where(d[..., 1] > 0, (0.3 - o[1]) / np.where(d[..., 1] > 0, d[..., 1], 1),
                            np.inf)
            subject = np.zeros((H, W), bool)
            for c, r, subj in spheres:
                b = d @ (o - c)
                disc = b * b - (o - c) @ (o - c) + r * r
                s = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
                nearer = (s > 0) & (s < best)
                best = np.where(nearer, s, best)
                subject = np.where(nearer, subj, subject)
            row.append(subject)
        out.append(np.stack(row))
    return np.stack(out)


def test_subject_masks_match_an_independent_projection_and_round_trip(tmp_path):
    """Both splits carry ``[F, V, H, W]`` masks at their frame times -- sharp although the
    training frames are exposure-blurred -- equal pixel for pixel to an analytic
    projection (moving objects and ``subject: true`` count, the floor and the static
    prop do not, occlusion included), and ``read_dataset`` returns them unchanged."""
    path = ensure_dataset(_mask_scene(), tmp_path)
    back = read_dataset(path)
    for name in ("train", "validation"):
        split = back.splits[name]
        assert (path / name / "mask").is_dir()
        assert split.masks.shape == (len(split.frame_times), split.n_views, 24, 32)
        ref = _independent_masks(split.cameras, split.frame_times)
        np.testing.assert_array_equal(split.masks, ref)
        assert 0.02 < ref.mean() < 0.5 and (ref[0] != ref[-2]).any()   # something moved
    ds = simulate_dataset(_mask_scene())
    for name in ("train", "validation"):
        np.testing.assert_array_equal(ds.splits[name].masks, back.splits[name].masks)


def test_datasets_cached_without_masks_are_not_reused(tmp_path):
    """A dataset cached by simulator version 1 (no masks) sits at the version-1 path;
    the current version hashes to another folder, so it is simulated again, with masks."""
    from eventrecon.sim.config import config_hash

    cfg = tiny(name="old", events=[], frames=[])
    old = tmp_path / f"old-{config_hash(cfg, 1)}"
    (old / "train").mkdir(parents=True)
    (old / "meta.json").write_text("{}")
    assert pipeline.SIM_VERSION >= 2
    path = ensure_dataset(cfg, tmp_path)
    assert path != old and path.name.startswith("old-")
    assert read_dataset(path).splits["train"].masks is not None


def test_frames_and_ground_truth_are_area_averaged_pixels_events_unchanged():
    """``frame_supersample=s``: every frame, background and ground-truth pixel is the mean
    of an s×s grid of rays over the pixel (the encoded mean of the linear radiance), while
    the events stay those of the ``supersample`` signal."""
    from eventrecon.common.colour import linear_to_srgb
    from eventrecon.sim.raytrace import PixelRenderer
    from eventrecon.sim.spec import build_cameras, parse_spec

    ideal = {"events": [], "frames": []}
    one = simulate_dataset(tiny(**ideal))
    four = simulate_dataset(tiny(frame_supersample=4, **ideal))
    for a, b in zip(one.splits["train"].events, four.splits["train"].events):
        assert np.array_equal(a.t, b.t) and np.array_equal(a.p, b.p)
    spec = parse_spec(tiny(frame_supersample=4, **ideal))
    _, held = build_cameras(spec)
    t = float(four.splits["validation"].frame_times[1]) / 1000.0  # normalised time
    finer = held.select([0])  # the 4x4 sub-pixel rays as the pixels of a 4x finer camera
    finer.K = finer.K.clone()
    finer.K[:, :2] *= 4.0
    finer.K[:, :2, 2] += 1.5  # pixel centres of the fine grid: (4u + 1.5, 4v + 1.5)
    finer.width, finer.height = held.width * 4, held.height * 4
    img = PixelRenderer(spec.scene, finer, 1).image(0, t).numpy()
    area = img.reshape(held.height, 4, held.width, 4, 3).mean(axis=(1, 3))
    gt = four.splits["validation"].frames[1, 0]
    assert np.abs(gt.astype(int) - linear_to_srgb(area).astype(int)).max() <= 1
    centre = one.splits["validation"].frames[1, 0]
    assert (gt != centre).any()  # the edges differ from the pixel-centre render


def test_heldout_camera_azimuth_is_configurable():
    """``rig.heldout_azimuth_deg``: the held-out camera's azimuth on the ring (default half
    way between training cameras 0 and 1); same radius, height and target as the ring."""
    import math

    from eventrecon.sim.spec import build_cameras, parse_spec

    def azimuth(cams, i: int) -> float:
        c = cams.c2w[i, :3, 3].numpy()
        return math.degrees(math.atan2(c[0], c[2])) % 360.0

    cfg = tiny()
    train, held = build_cameras(parse_spec(cfg))
    n = len(train.names)
    gap = (azimuth(train, 1) - azimuth(train, 0)) % 360.0
    assert gap == pytest.approx(360.0 / n)
    assert (azimuth(held, 0) - azimuth(train, 0)) % 360.0 == pytest.approx(180.0 / n)
    cfg["rig"] = {**cfg.get("rig", {}), "heldout_azimuth_deg": 45.0}
    train2, held2 = build_cameras(parse_spec(cfg))
    assert (azimuth(held2, 0) - azimuth(train2, 0)) % 360.0 == pytest.approx(45.0)
    r = np.linalg.norm(held2.c2w[0, :3, 3].numpy())
    assert r == pytest.approx(np.linalg.norm(train2.c2w[0, :3, 3].numpy()))
