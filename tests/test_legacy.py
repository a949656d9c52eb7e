"""The earlier EventNeRF layout: one moving camera, one events npz, ~1000 poses."""

from __future__ import annotations

import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from eventrecon.common.errors import InputError
from eventrecon.data.layout import read_split
from eventrecon.data.legacy import is_legacy_split, read_legacy_split, slerp_c2w

N_POSES, H, W = 41, 12, 16


def _ry(th: float) -> np.ndarray:
    c, s = math.cos(th), math.sin(th)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _orbit(th: float) -> np.ndarray:
    """c2w of a camera on a circle of radius 3 looking at the origin (rotation Ry(θ)·R0)."""
    m = np.eye(4)
    m[:3, :3] = _ry(th) @ np.diag([-1.0, 1.0, -1.0])
    m[:3, 3] = _ry(th) @ np.array([0.0, 0.0, 3.0])
    return m


def write_legacy(split: Path, t_max: float = 5.0, images: bool = True) -> dict:
    rng = np.random.default_rng(0)
    for sub in ("pose", "intrinsics", "events", "rgb"):
        (split / sub).mkdir(parents=True)
    angles = np.linspace(0, math.pi, N_POSES)
    intr = np.zeros((5, 4))
    intr[:3, :3] = [[20, 0, 7.5], [0, 20, 5.5], [0, 0, 1]]
    intr[3, 3], intr[4] = 1, [-0.1, 0.01, 0, 0]
    imgs = rng.integers(0, 256, (N_POSES, H, W, 3), dtype=np.uint8)
    for i, th in enumerate(angles):
        np.savetxt(split / "pose" / f"r_{i:05d}.txt", _orbit(th), fmt="%.17g")
        np.savetxt(split / "intrinsics" / f"r_{i:05d}.txt", intr)
        if images:
            iio.imwrite(split / "rgb" / f"r_{i:05d}.png", imgs[i])
    n = 3000
    t = np.sort(rng.uniform(0, t_max, n))
    t[-1] = t_max
    ev = dict(x=rng.integers(0, W, n), y=rng.integers(0, H, n), t=t, p=rng.choice([-1, 1], n))
    np.savez(split / "events" / "test_lin_log.npz", **ev)
    return dict(angles=angles, imgs=imgs, ev=ev, t_max=t_max)


def test_reads_poses_events_and_times(tmp_path):
    truth = write_legacy(tmp_path / "train")
    assert is_legacy_split(tmp_path / "train")
    sp = read_legacy_split(tmp_path / "train")
    assert (len(sp.poses), sp.poses.width, sp.poses.height) == (N_POSES, W, H)
    np.testing.assert_array_equal(sp.poses.c2w.numpy()[7], _orbit(truth["angles"][7]))
    np.testing.assert_array_equal(sp.poses.dist.numpy()[0], [-0.1, 0.01, 0, 0, 0])
    np.testing.assert_allclose(sp.pose_times, np.arange(N_POSES) * 25.0, rtol=0, atol=1e-12)
    # t rescaled by 1000 / t_max, coordinates and polarities unchanged
    np.testing.assert_allclose(sp.events.t, truth["ev"]["t"] * 200.0, rtol=1e-15)
    assert sp.events.t[-1] == 1000.0
    np.testing.assert_array_equal(sp.events.x, truth["ev"]["x"])
    np.testing.assert_array_equal(sp.events.p, truth["ev"]["p"])
    np.testing.assert_array_equal(sp.frames, truth["imgs"])


def test_pose_at_times_interpolates_rotation_exactly(tmp_path):
    truth = write_legacy(tmp_path / "train", images=False)
    sp = read_legacy_split(tmp_path / "train")
    assert (sp.poses.width, sp.poses.height) == (346, 260)  # the earlier loader's default
    # at the pose times: the poses themselves
    at = sp.pose_at(sp.pose_times).numpy()
    np.testing.assert_allclose(at, sp.poses.c2w.numpy(), atol=1e-12)
    # between poses: the rotation of the orbit at the interpolated angle (slerp is exact
    # for a rotation about one axis), translation on the chord
    t = np.array([12.5, 333.3, 987.0])
    s = t / 1000 * (N_POSES - 1)
    th = np.interp(s, np.arange(N_POSES), truth["angles"])
    got = sp.pose_at(t).numpy()
    for k in range(3):
        np.testing.assert_allclose(got[k, :3, :3], _orbit(th[k])[:3, :3], atol=1e-12)
        i0 = int(s[k])
        w = s[k] - i0
        ta, tb = (_orbit(truth["angles"][i])[:3, 3] for i in (i0, i0 + 1))
        chord = (1 - w) * ta + w * tb
        np.testing.assert_allclose(got[k, :3, 3], chord, atol=1e-12)
    np.testing.assert_array_equal(sp.pose_index(np.array([0.0, 12.4, 12.6, 1000.0])),
                                  [0, 0, 1, N_POSES - 1])


def test_slerp_against_scipy():
    from scipy.spatial.transform import Rotation, Slerp
    rng = np.random.default_rng(5)
    ra, rb = Rotation.random(2, random_state=rng)
    a, b = np.eye(4), np.eye(4)
    a[:3, :3], b[:3, :3] = ra.as_matrix(), rb.as_matrix()
    w = np.linspace(0, 1, 7)
    ref = Slerp([0, 1], Rotation.concatenate([ra, rb]))(w).as_matrix()
    got = slerp_c2w(np.repeat(a[None], 7, 0), np.repeat(b[None], 7, 0), w)
    np.testing.assert_allclose(got[:, :3, :3], ref, atol=1e-12)


def test_published_multiview_split_is_not_legacy(tmp_path):
    from test_layout import write_split
    write_split(tmp_path / "train", n_events=5)
    assert not is_legacy_split(tmp_path / "train")
    assert read_split(tmp_path / "train").n_views == 3


def test_two_event_files_is_input_error(tmp_path):
    write_legacy(tmp_path / "train", images=False)
    np.savez(tmp_path / "train" / "events" / "extra.npz", x=[0], y=[0], t=[0.0], p=[1])
    with pytest.raises(InputError, match=r"events: <folder>: expected exactly one \.npz"):
        read_legacy_split(tmp_path / "train")


def test_reading_legacy_as_multiview_names_the_right_reader(tmp_path):
    write_legacy(tmp_path / "train", images=True)
    with pytest.raises(InputError, match=r"train: <layout>: .*read_legacy_split"):
        read_split(tmp_path / "train")
