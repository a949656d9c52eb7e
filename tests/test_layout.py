"""Reader of the published layout against a scene written here by hand.

The scene is written with numpy.savetxt / np.savez / imageio only (never the project's
writer), so the reader is not tested against code that shares its assumptions.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from eventrecon.common.errors import InputError
from eventrecon.data.batcher import RayBatcher, Segment
from eventrecon.data.layout import read_dataset, read_split
from eventrecon.data.selection import select_views
from eventrecon.data.views import view_key
from eventrecon.engine import build
from eventrecon.render.cameras import load_camdict
from eventrecon.render.distortion import distort, undistort

H, W, V = 20, 30, 3
FRAME_TIMES = (0, 200, 1000)
DIST = np.array([-0.4, 0.2, 1e-3, -2e-3, -0.05])


def _c2w(i: int, n: int) -> np.ndarray:
    """A camera on a ring of radius 2.5 looking at the origin (OpenCV axes, up = −y)."""
    az = 2 * math.pi * i / n
    eye = 2.5 * np.array([math.sin(az), -0.3, math.cos(az)])
    z = -eye / np.linalg.norm(eye)
    x = np.cross(z, [0.0, -1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, eye
    return m


def write_split(split: Path, seed: int = 0, n_events: int = 500, views: int = V,
                intr_shape: str = "5x5", camdict: bool = False, grey: bool = False) -> dict:
    """Write one split in the published layout; return what was written."""
    rng = np.random.default_rng(seed)
    truth: dict = {"K": [], "dist": [], "c2w": [], "events": [], "frames": [], "bg": []}
    for sub in ("intrinsics", "pose", "events", "background"):
        (split / sub).mkdir(parents=True, exist_ok=True)
    for v in range(views):
        name = f"{v:02d}"
        K = np.array([[25.0 + v, 0, 14.5], [0, 26.0 + v, 9.5], [0, 0, 1]])
        dist = DIST * (1 + 0.1 * v) if intr_shape != "4x4" else np.zeros(5)
        if intr_shape == "5x5":  # K top-left, last row k1 k2 p1 p2 k3
            m = np.zeros((5, 5))
            m[:3, :3], m[3, 3], m[4] = K, 1, dist
        elif intr_shape == "5x4":  # last row k1 k2 p1 p2
            m = np.zeros((5, 4))
            m[:3, :3], m[3, 3], m[4] = K, 1, dist[:4]
            dist = np.r_[dist[:4], 0.0]
        else:
            m = np.eye(4)
            m[:3, :3] = K
        np.savetxt(split / "intrinsics" / f"{name}.txt", m)
        c2w = _c2w(v, views)
        np.savetxt(split / "pose" / f"{name}.txt", c2w, fmt="%.17g")
        t = np.sort(rng.uniform(0, 1000, n_events))
        t[0], t[-1] = 0.0, 1000.0
        ev = dict(x=rng.integers(0, W, n_events), y=rng.integers(0, H, n_events),
                  t=t, p=rng.choice([-1, 1], n_events))
        np.savez(split / "events" / f"{name}.npz", **ev)
        bg = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        iio.imwrite(split / "background" / f"{name}.png", bg)
        for key, value in (("K", K), ("dist", dist), ("c2w", c2w), ("events", ev), ("bg", bg)):
            truth[key].append(value)
    for ft in FRAME_TIMES:
        d = split / "rgb" / f"{ft:04d}"
        d.mkdir(parents=True)
        imgs = []
        for v in range(views):
            shape = (H, W) if grey else (H, W, 3)
            img = rng.integers(0, 256, shape, dtype=np.uint8)
            iio.imwrite(d / f"{v:02d}.png", img)
            imgs.append(img)
        truth["frames"].append(np.stack(imgs))
    if camdict:
        cd = {}
        for v in range(views):
            K4 = np.eye(4)
            K4[:3, :3] = truth["K"][v]
            cd[f"{v:02d}.png"] = {"K": K4.ravel().tolist(),
                                  "W2C": np.linalg.inv(truth["c2w"][v]).ravel().tolist(),
                                  "dist": list(truth["dist"][v]), "img_size": [W, H]}
        (split / "camdict.json").write_text(json.dumps(cd))
    return truth


@pytest.fixture()
def scene(tmp_path: Path) -> tuple[Path, dict]:
    truth = write_split(tmp_path / "scene" / "train", seed=1)
    write_split(tmp_path / "scene" / "validation", seed=2, views=2, n_events=10)
    (tmp_path / "scene" / "meta.json").write_text(json.dumps({"tonemap_eps": 0.03,
                                                              "decay": 0.93}))
    return tmp_path / "scene", truth


def test_reads_every_value_exactly(scene):
    root, truth = scene
    ds = read_dataset(root)
    assert set(ds.splits) == {"train", "validation"}
    assert ds.meta == {"tonemap_eps": 0.03, "decay": 0.93}
    sp = ds.splits["train"]
    cams = sp.cameras
    assert (cams.width, cams.height, len(cams)) == (W, H, V)
    assert cams.names == ["00", "01", "02"]
    # the files' principal point is the authors' (pixel centres at i + 0.5): ours is half
    # a pixel less (eventrecon.render.cameras.K_from_file)
    want = np.stack(truth["K"]).copy()
    want[:, :2, 2] -= 0.5
    np.testing.assert_array_equal(cams.K.numpy(), want)
    np.testing.assert_allclose(cams.dist.numpy(), np.stack(truth["dist"]), rtol=1e-15)
    np.testing.assert_array_equal(cams.c2w.numpy(), np.stack(truth["c2w"]))
    np.testing.assert_array_equal(sp.frame_times, FRAME_TIMES)
    assert sp.frames.shape == (3, V, H, W, 3) and sp.frames.dtype == np.uint8
    np.testing.assert_array_equal(sp.frames, np.stack(truth["frames"]))
    np.testing.assert_array_equal(sp.background, np.stack(truth["bg"]))
    for ev, ref in zip(sp.events, truth["events"]):
        assert (ev.x.dtype, ev.y.dtype, ev.t.dtype, ev.p.dtype) == (
            np.int16, np.int16, np.float64, np.int8)
        for k in "xytp":
            np.testing.assert_array_equal(getattr(ev, k), ref[k])
    assert ds.splits["validation"].n_views == 2
    assert sum(len(e) for e in ds.splits["validation"].events) == 20


@pytest.mark.parametrize("shape", ["5x4", "4x4"])
def test_other_intrinsics_shapes(tmp_path, shape):
    truth = write_split(tmp_path / "s", intr_shape=shape, n_events=5)
    sp = read_split(tmp_path / "s")
    np.testing.assert_allclose(sp.cameras.dist.numpy(), np.stack(truth["dist"]), rtol=1e-15)
    if shape == "4x4":
        assert float(sp.cameras.dist.abs().max()) == 0.0


def test_camdict_only_equals_txt_cameras(tmp_path):
    write_split(tmp_path / "s", camdict=True, n_events=5)
    a = read_split(tmp_path / "s").cameras
    for sub in ("intrinsics", "pose"):
        for f in (tmp_path / "s" / sub).iterdir():
            f.unlink()
        (tmp_path / "s" / sub).rmdir()
    b = read_split(tmp_path / "s").cameras
    assert torch.allclose(a.K, b.K) and torch.allclose(a.dist, b.dist)
    assert float((a.c2w - b.c2w).abs().max()) < 1e-12
    assert b.names == ["00", "01", "02"]


def test_txt_cameras_take_precedence_over_disagreeing_camdict(tmp_path, caplog):
    truth = write_split(tmp_path / "s", camdict=True, n_events=5)
    cd = json.loads((tmp_path / "s" / "camdict.json").read_text())
    cd["01.png"]["K"][0] += 10.0  # fx of view 1 off by 10 px
    (tmp_path / "s" / "camdict.json").write_text(json.dumps(cd))
    with caplog.at_level("WARNING"):
        cams = read_split(tmp_path / "s").cameras
    want = np.stack(truth["K"]).copy()
    want[:, :2, 2] -= 0.5                        # the files' pixel centres are at i + 0.5
    np.testing.assert_array_equal(cams.K.numpy(), want)
    assert "camdict.json: K disagrees with intrinsics/ + pose/" in caplog.text


def test_pixel_rays_are_the_authors_rays_through_the_half_pixel(tmp_path):
    """The authors (and NeRF++) cast pixel (u, v)'s ray through (u + ½, v + ½) with the
    file's K; ours through the pixel centre (u, v) must be the same ray."""
    truth = write_split(tmp_path / "s", n_events=5)
    cams = read_split(tmp_path / "s").cameras
    uv = cams.pixel_grid()                       # integer pixel centres, ours
    view = torch.zeros(len(uv), dtype=torch.long)
    ours = cams.pixel_directions(view, uv)       # undistorted camera-frame directions
    K = truth["K"][0]
    x = (uv[:, 0].numpy() + 0.5 - K[0, 2]) / K[0, 0]
    y = (uv[:, 1].numpy() + 0.5 - K[1, 2]) / K[1, 1]
    xy_authors = undistort(torch.from_numpy(np.stack([x, y], -1)), cams.dist[view])
    np.testing.assert_allclose(ours[:, :2].numpy(), xy_authors.numpy(), atol=1e-9)


def test_greyscale_frames_are_bayer_raw(tmp_path):
    truth = write_split(tmp_path / "s", grey=True, n_events=5)
    sp = read_split(tmp_path / "s")
    assert sp.frames.shape == (3, V, H, W)
    np.testing.assert_array_equal(sp.frames, np.stack(truth["frames"]))


def test_views_match_by_trailing_number(tmp_path):
    write_split(tmp_path / "s", n_events=5)
    for f in sorted((tmp_path / "s" / "events").iterdir()):
        f.rename(f.with_name("r_" + f.name))  # events/r_00.npz matches intrinsics/00.txt
    assert len(read_split(tmp_path / "s").events) == V
    assert view_key("r_0007") == view_key("7") == 7


def test_frame_folders_sorted_by_time_not_name(tmp_path):
    write_split(tmp_path / "s", n_events=5)
    # "50" sorts after "1000" as a string; frame times must sort numerically
    (tmp_path / "s" / "rgb" / "0200").rename(tmp_path / "s" / "rgb" / "50")
    np.testing.assert_array_equal(read_split(tmp_path / "s").frame_times, [0, 50, 1000])


def test_masks_per_frame(tmp_path):
    write_split(tmp_path / "s", n_events=5)
    rng = np.random.default_rng(3)
    truth = rng.random((3, V, H, W)) > 0.5
    for fi, ft in enumerate(FRAME_TIMES):
        d = tmp_path / "s" / "mask" / f"{ft:04d}"
        d.mkdir(parents=True)
        for v in range(V):
            iio.imwrite(d / f"{v:02d}.png", truth[fi, v].astype(np.uint8) * 255)
    np.testing.assert_array_equal(read_split(tmp_path / "s").masks, truth)


def test_static_masks_also_weight_the_training_losses_per_frame_masks_do_not(tmp_path):
    write_split(tmp_path / "s", n_events=5)
    rng = np.random.default_rng(4)
    grey = rng.integers(0, 256, (V, H, W)).astype(np.uint8)
    (tmp_path / "s" / "mask").mkdir()
    for v in range(V):                   # an RGB PNG: the first channel is the weight
        rgb = np.stack([grey[v], 255 - grey[v], np.zeros_like(grey[v])], -1)
        iio.imwrite(tmp_path / "s" / "mask" / f"{v:02d}.png", rgb)
    split = read_split(tmp_path / "s")
    np.testing.assert_array_equal(split.loss_mask, grey.astype(np.float32) / 255)
    assert split.masks.shape == (len(FRAME_TIMES), V, H, W)
    assert select_views(split, 2).loss_mask.shape == (2, H, W)
    batch = RayBatcher(split, Segment(0.0, 1000.0), decay=1.0, bayer=True).sample(
        64, torch.Generator().manual_seed(0))        # each ray's weight: its pixel's
    assert torch.equal(batch["weight"], torch.from_numpy(split.loss_mask)[
        batch["view"], batch["row"], batch["col"]])
    write_split(tmp_path / "f", n_events=5)   # per-frame masks: subject metrics only
    for ft in FRAME_TIMES:
        d = tmp_path / "f" / "mask" / f"{ft:04d}"
        d.mkdir(parents=True)
        for v in range(V):
            iio.imwrite(d / f"{v:02d}.png", grey[v])
    assert read_split(tmp_path / "f").loss_mask is None


def test_rig_camdict_fixture_is_plausible_davis346():
    cams = load_camdict(Path(__file__).parent / "data" / "rig_camdict.json")
    assert (len(cams), cams.width, cams.height) == (6, 346, 260)
    r = cams.centers.norm(dim=-1)
    assert float((r - 2.5).abs().max()) < 0.05
    assert float((cams.dist[:, 0] + 0.4).abs().max()) < 0.05
    # every camera sees the origin inside its image
    uv, z = cams.project(torch.zeros(6, 3, dtype=torch.float64), torch.arange(6))
    assert bool((z > 0).all())
    assert bool(((uv[:, 0] > 0) & (uv[:, 0] < 345) & (uv[:, 1] > 0) & (uv[:, 1] < 259)).all())
    # strong distortion: a corner ray is displaced by several pixels
    xy = torch.tensor([[0.5, 0.4]], dtype=torch.float64)
    assert float((distort(xy, cams.dist[:1]) - xy).abs().max() * cams.K[0, 0, 0]) > 5


def test_image_rays_are_cached_and_exact():
    """Full-image rays of the strongly distorted rig: cached, and each pixel's ray
    projects back onto that pixel to 1e-4 px (k1 ≈ −0.4)."""
    import time
    cams = load_camdict(Path(__file__).parent / "data" / "rig_camdict.json")
    t0 = time.perf_counter()
    o, d = cams.image_rays(2)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    o2, d2 = cams.image_rays(2)
    second = time.perf_counter() - t0
    assert torch.equal(d, d2) and second < first / 5
    uv = cams.pixel_grid()
    view = torch.full((len(uv),), 2, dtype=torch.long)
    back, z = cams.project(o.double() + 2.0 * d.double(), view)
    assert (z > 0).all() and float((back - uv).abs().max()) < 1e-3  # float32 rays
    xy = cams.pixel_directions(view, uv)[:, :2]  # float64 undistorted directions
    xd = distort(xy, cams.dist[view])
    u = cams.K[2, 0, 0] * xd[:, 0] + cams.K[2, 0, 2]
    v = cams.K[2, 1, 1] * xd[:, 1] + cams.K[2, 1, 2]
    assert float((torch.stack([u, v], -1) - uv).abs().max()) < 1e-4
    cams.c2w[2, 0, 3] += 0.5  # a camera changed in place is not served stale rays
    o3, _ = cams.image_rays(2)
    assert abs(float(o3[0, 0] - o[0, 0]) - 0.5) < 1e-6


def test_missing_train_split_is_input_error(tmp_path):
    (tmp_path / "scene" / "validation").mkdir(parents=True)
    with pytest.raises(InputError, match=r"train: <folder>: expected a train/ split"):
        read_dataset(tmp_path / "scene")


def test_large_event_file_loads_fast(tmp_path):
    """2·10^6 events per view: vectorised load + validation, no Python loop per event."""
    import time
    write_split(tmp_path / "s", n_events=5, views=1)
    n = 2_000_000
    rng = np.random.default_rng(0)
    np.savez(tmp_path / "s" / "events" / "00.npz", x=rng.integers(0, W, n, dtype=np.int16),
             y=rng.integers(0, H, n, dtype=np.int16), t=np.linspace(0, 1000, n),
             p=rng.choice(np.array([-1, 1], np.int8), n))
    t0 = time.perf_counter()
    sp = read_split(tmp_path / "s")
    assert len(sp.events[0]) == n
    assert time.perf_counter() - t0 < 3.0


def test_independent_dataset_trains(scene, tmp_path: Path):
    """The hand-written dataset trains through the user's path (``data.root=``): a few
    steps, finite losses, evaluated on its validation split."""
    from integration import TINY, TINY_NERF, tiny_config

    from eventrecon.engine import runner

    root, _ = scene
    cfg = tiny_config(tmp_path / "unused", "data=real", f"data.root={root}",
                      "trainer.max_steps=4", "data.eval_every_frames=1",
                      base=[t for t in TINY if not t.startswith("scene.")] + TINY_NERF)
    metrics = runner.run(cfg, tmp_path / "run")
    assert metrics["status"] == "ok" and metrics["steps"] == 5 * 4  # 4 per segment
    assert metrics["nonfinite_steps"] == 0 and math.isfinite(metrics["psnr"])
    assert metrics["views"] == V and metrics["segments"] == [[0.0, 210.0], [190.0, 410.0],
                                                             [390.0, 610.0], [590.0, 810.0],
                                                             [790.0, 1000.0]]
    props = build.scene_properties(cfg, read_dataset(root))
    # meta.json's eps and decay are overridden by data=real's, and Bayer comes from it
    assert (props.tonemap_eps, props.decay, props.bayer) == (0.03, 0.93, True)


def test_dataset_without_meta_needs_its_properties(scene, tmp_path: Path):
    """A published scene has no meta.json: eps/decay/Bayer must come from the config."""
    from integration import tiny_config

    from eventrecon.engine import runner

    root, _ = scene
    (root / "meta.json").unlink()
    cfg = tiny_config(tmp_path, f"data.root={root}")
    with pytest.raises(InputError, match=r"meta\.json: tonemap_eps, decay, bayer: expected .*"
                                         r"data=real"):
        runner.run(cfg, tmp_path / "run")
    cfg = tiny_config(tmp_path, f"data.root={root}", "data.tonemap_eps=0.05",
                      "data.decay=1.0", "data.bayer=false")
    props = build.scene_properties(cfg, read_dataset(root))
    assert (props.tonemap_eps, props.decay, props.bayer, props.segments) == (0.05, 1.0, False,
                                                                            None)


@pytest.mark.parametrize("missing", ["events", "rgb"])
def test_training_split_without_events_or_frames_is_one_line(scene, tmp_path: Path,
                                                             missing: str):
    import shutil

    from integration import tiny_config

    from eventrecon.engine import runner

    root, _ = scene
    shutil.rmtree(root / "train" / missing)
    cfg = tiny_config(tmp_path, "data=real", f"data.root={root}")
    with pytest.raises(InputError, match=rf"train/{missing}: <folder>: expected .*, got missing"):
        runner.run(cfg, tmp_path / "run")


def test_groundtruth_split_is_the_one_evaluated(scene, tmp_path: Path):
    """Published synthetic scenes carry sharp held-out renders in groundtruth/."""
    from eventrecon.data.selection import heldout_split

    root, _ = scene
    assert heldout_split(read_dataset(root)).root == root / "validation"
    write_split(root / "groundtruth", seed=9, views=2, n_events=10)
    ds = read_dataset(root)
    assert set(ds.splits) == {"train", "validation", "groundtruth"}
    assert heldout_split(ds).root == root / "groundtruth"
