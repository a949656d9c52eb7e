"""Pinhole cameras with OpenCV lens distortion, rays, projection and rigs.

Conventions (the published dataset's):

- camera axes are OpenCV's: x right, y down, z forward (the viewing direction);
- ``c2w`` is the 4×4 camera-to-world matrix, world units normalised so the subject
  lies in the unit sphere;
- pixel ``(u, v)`` = (column, row); integer coordinates are pixel *centres*
  (OpenCV), so pixel ``i`` covers ``[i - 0.5, i + 0.5)``;
- the intrinsics *files* (``intrinsics/*.txt``, ``camdict.json``) follow the authors'
  code and NeRF++, which cast pixel ``(u, v)``'s ray through ``(u + 0.5, v + 0.5)``: their
  principal point lies half a pixel further than ours (:data:`FILE_PIXEL_CENTRE`;
  :func:`K_from_file` / :func:`K_to_file` convert, and every reader and writer of those
  files goes through them);
- distortion ``dist = (k1, k2, p1, p2, k3)`` (OpenCV's model, :mod:`.distortion`) acts
  on normalised coordinates ``(x, y) = (X/Z, Y/Z)``, then ``u = fx x_d + cx``,
  ``v = fy y_d + cy``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from eventrecon.common.errors import InputError
from eventrecon.render.distortion import distort, undistort

__all__ = [
    "Cameras",
    "look_at",
    "ring_rig",
    "cameras_from_camdict",
    "check_intrinsics",
    "check_rigid",
    "RIGID_TOL",
    "cameras_to_camdict",
    "FILE_PIXEL_CENTRE",
    "K_from_file",
    "K_to_file",
]

#: Where the intrinsics files put pixel ``i``'s centre: at ``i + 0.5`` (the authors'
#: ``get_rays_single_image`` and NeRF++ add half a pixel before applying ``K⁻¹``).
FILE_PIXEL_CENTRE = 0.5


def K_from_file(K: np.ndarray) -> np.ndarray:
    """``[3, 3]`` intrinsics as stored in the files → ours: the principal point moves by
    ``−FILE_PIXEL_CENTRE`` so that our ray through pixel centre ``(u, v)`` is the file
    convention's ray through ``(u + ½, v + ½)``.

    >>> K_from_file(np.array([[100.0, 0, 50.0], [0, 100.0, 40.0], [0, 0, 1]]))[:2, 2].tolist()
    [49.5, 39.5]
    """
    out = np.array(K, dtype=np.float64, copy=True)
    out[:2, 2] -= FILE_PIXEL_CENTRE
    return out


def K_to_file(K: np.ndarray) -> np.ndarray:
    """Inverse of :func:`K_from_file`."""
    out = np.array(K, dtype=np.float64, copy=True)
    out[:2, 2] += FILE_PIXEL_CENTRE
    return out


@dataclass
class Cameras:
    """A set of ``V`` pinhole cameras sharing one image size.

    Attributes:
        K: ``[V, 3, 3]`` intrinsics (float64).
        dist: ``[V, 5]`` OpenCV distortion ``(k1, k2, p1, p2, k3)``.
        c2w: ``[V, 4, 4]`` camera-to-world, OpenCV axes.
        width, height: image size in pixels.
        names: one name per view (file stem in the dataset layout).
    """

    K: Tensor
    dist: Tensor
    c2w: Tensor
    width: int
    height: int
    names: list[str] = field(default_factory=list)
    #: per-view full-image rays, keyed by the view's parameters (see :meth:`image_rays`)
    _rays_cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.K = torch.as_tensor(self.K, dtype=torch.float64)
        self.dist = torch.as_tensor(self.dist, dtype=torch.float64)
        self.c2w = torch.as_tensor(self.c2w, dtype=torch.float64)
        v = self.K.shape[0]
        if self.K.shape != (v, 3, 3) or self.dist.shape != (v, 5) or self.c2w.shape != (v, 4, 4):
            raise InputError(
                "cameras", "K/dist/c2w", "shapes [V,3,3], [V,5], [V,4,4]",
                f"{tuple(self.K.shape)}, {tuple(self.dist.shape)}, {tuple(self.c2w.shape)}",
            )
        if not self.names:
            self.names = [f"{i:02d}" for i in range(v)]

    def __len__(self) -> int:
        return int(self.K.shape[0])

    def __getstate__(self) -> dict:
        """Pickle without the ray cache (it is rebuilt on demand)."""
        return {**self.__dict__, "_rays_cache": {}}

    def select(self, idx: Sequence[int]) -> Cameras:
        """The cameras at positions ``idx`` (in that order)."""
        ii = torch.as_tensor(list(idx), dtype=torch.long)
        return Cameras(self.K[ii], self.dist[ii], self.c2w[ii], self.width, self.height,
                       [self.names[i] for i in ii.tolist()])

    @property
    def centers(self) -> Tensor:
        """``[V, 3]`` camera centres in world coordinates."""
        return self.c2w[:, :3, 3]

    def pixel_directions(self, view: Tensor, uv: Tensor) -> Tensor:
        """Camera-frame ray directions ``(x, y, 1)`` through pixel positions.

        Args:
            view: ``[N]`` long, camera index per point.
            uv: ``[N, 2]`` pixel coordinates (column, row), possibly fractional.

        Returns:
            ``[N, 3]`` float64 directions in camera axes with unit z (undistorted).
        """
        K = self.K[view]
        xd = (uv[:, 0].double() - K[:, 0, 2]) / K[:, 0, 0]
        yd = (uv[:, 1].double() - K[:, 1, 2]) / K[:, 1, 1]
        xy = undistort(torch.stack([xd, yd], -1), self.dist[view])
        return torch.cat([xy, torch.ones_like(xy[:, :1])], dim=-1)

    def rays(self, view: Tensor, uv: Tensor) -> tuple[Tensor, Tensor]:
        """World-space rays through pixel positions.

        Args:
            view: ``[N]`` long camera indices.
            uv: ``[N, 2]`` pixel coordinates.

        Returns:
            ``(origins [N, 3], directions [N, 3])`` float32, directions of unit length,
            so the ray parameter is metric distance from the camera centre.
        """
        d_cam = self.pixel_directions(view, uv)
        R = self.c2w[view, :3, :3]
        d = torch.einsum("nij,nj->ni", R, d_cam)
        d = d / d.norm(dim=-1, keepdim=True)
        o = self.c2w[view, :3, 3]
        return o.float(), d.float()

    def pixel_grid(self) -> Tensor:
        """``[H*W, 2]`` integer pixel centres (u, v) in row-major order."""
        v, u = torch.meshgrid(torch.arange(self.height), torch.arange(self.width), indexing="ij")
        return torch.stack([u.reshape(-1), v.reshape(-1)], dim=-1).double()

    def image_rays(self, view: int) -> tuple[Tensor, Tensor]:
        """All ``H*W`` rays of one view, row-major: ``([H*W, 3], [H*W, 3])``.

        Cached per view (the Newton undistortion of every pixel is the costly part); the
        key holds the view's ``K``, ``dist``, ``c2w`` and the image size, so a camera
        changed in place is recomputed. Returns copies, safe to modify.
        """
        key = (int(view), self.width, self.height,
               *torch.cat([self.K[view].flatten(), self.dist[view],
                           self.c2w[view].flatten()]).tolist())
        hit = self._rays_cache.get(key)
        if hit is None:
            uv = self.pixel_grid()
            hit = self.rays(torch.full((uv.shape[0],), int(view), dtype=torch.long), uv)
            if len(self._rays_cache) >= 64:
                self._rays_cache.pop(next(iter(self._rays_cache)))
            self._rays_cache[key] = hit
        return hit[0].clone(), hit[1].clone()

    def project(self, xyz: Tensor, view: Tensor) -> tuple[Tensor, Tensor]:
        """Project world points into their cameras (with distortion).

        Args:
            xyz: ``[N, 3]`` world points.
            view: ``[N]`` long camera index per point.

        Returns:
            ``(uv [N, 2], depth [N])`` pixel coordinates and camera-frame z, float64.
        """
        w2c = torch.linalg.inv(self.c2w[view])
        p = torch.einsum("nij,nj->ni", w2c[:, :3, :3], xyz.double()) + w2c[:, :3, 3]
        z = p[:, 2]
        xy = distort(p[:, :2] / z[:, None], self.dist[view])
        K = self.K[view]
        u = K[:, 0, 0] * xy[:, 0] + K[:, 0, 1] * xy[:, 1] + K[:, 0, 2]
        v = K[:, 1, 1] * xy[:, 1] + K[:, 1, 2]
        return torch.stack([u, v], -1), z


def look_at(eye: Tensor, target: Tensor, up: Tensor) -> Tensor:
    """Camera-to-world matrix (OpenCV axes) of a camera at ``eye`` looking at ``target``.

    ``z = normalize(target − eye)``, ``x = normalize(z × up)`` (so ``up`` points to −y
    in the image), ``y = z × x``.

    Args:
        eye, target, up: ``[3]`` vectors.

    Returns:
        ``[4, 4]`` float64 c2w.
    """
    eye, target, up = (torch.as_tensor(a, dtype=torch.float64) for a in (eye, target, up))
    z = target - eye
    z = z / z.norm()
    x = torch.linalg.cross(z, up)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    m = torch.eye(4, dtype=torch.float64)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, z, eye
    return m


def ring_rig(
    n_views: int,
    width: int,
    height: int,
    radius: float = 2.5,
    elevation_deg: float = 15.0,
    fov_deg: float = 40.0,
    target: Sequence[float] = (0.0, -0.25, 0.0),
    azimuth_offset_deg: float = 0.0,
    dist: Sequence[float] = (0.0, 0.0, 0.0, 0.0, 0.0),
    names: Sequence[str] | None = None,
) -> Cameras:
    """``n_views`` cameras evenly on a horizontal ring, all looking at ``target``.

    World up is −y (OpenCV-style world, as in the published data: the clipping cylinder's
    axis is y with the floor at larger y). Camera ``i`` sits at azimuth
    ``azimuth_offset + 360°·i/n`` around the y axis, ``radius`` from ``target`` and
    ``elevation_deg`` above it; focal length from the horizontal field of view.

    Returns:
        :class:`Cameras` with ``V = n_views``.
    """
    tgt = torch.tensor(target, dtype=torch.float64)
    up = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    K = torch.tensor([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]],
                     dtype=torch.float64)
    el = math.radians(elevation_deg)
    c2w = []
    for i in range(n_views):
        az = math.radians(azimuth_offset_deg + 360.0 * i / n_views)
        eye = tgt + radius * torch.tensor(
            [math.cos(el) * math.sin(az), -math.sin(el), math.cos(el) * math.cos(az)],
            dtype=torch.float64)
        c2w.append(look_at(eye, tgt, up))
    return Cameras(K.expand(n_views, 3, 3).clone(),
                   torch.tensor(dist, dtype=torch.float64).expand(n_views, 5).clone(),
                   torch.stack(c2w), width, height,
                   list(names) if names is not None else [])


#: Tolerance of the rigidity check: ``max |RᵀR − I| ≤ tol`` and ``|det R − 1| ≤ tol``.
RIGID_TOL: float = 1e-3


def check_intrinsics(K: np.ndarray, where: str | Path, field: str = "K") -> None:
    """Raise unless ``K [3, 3]`` is ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``, finite,
    with ``fx, fy > 0``."""
    K = np.asarray(K, dtype=np.float64)
    ok = (K.shape == (3, 3) and bool(np.isfinite(K).all())
          and np.allclose(K[2], [0.0, 0.0, 1.0], atol=1e-6) and abs(K[1, 0]) < 1e-9
          and K[0, 0] > 0 and K[1, 1] > 0)
    if not ok:
        raise InputError(where, field, "[[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0",
                         np.array2string(K, precision=3).replace("\n", ""))


def check_rigid(m: np.ndarray, where: Path | str, field: str = "pose",
                tol: float = RIGID_TOL) -> None:
    """Raise ``non-rigid pose`` unless ``m [4, 4]`` is a rotation + translation.

    Checks ``max |RᵀR − I| ≤ tol``, ``|det R − 1| ≤ tol`` and the last row
    ``(0, 0, 0, 1)`` (to ``tol``).
    """
    m = np.asarray(m, dtype=np.float64)
    if m.shape != (4, 4):
        raise InputError(where, field, "a 4×4 matrix", "×".join(map(str, m.shape)))
    if not np.isfinite(m).all():
        raise InputError(where, field, "finite numbers", "NaN or inf")
    R = m[:3, :3]
    ortho = float(np.abs(R.T @ R - np.eye(3)).max())
    det = float(np.linalg.det(R))
    bottom = float(np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max())
    if ortho > tol or abs(det - 1.0) > tol or bottom > tol:
        raise InputError(where, field,
                         f"a rigid transform (R orthonormal, det R = +1, "
                         f"last row 0 0 0 1, within {tol:g})",
                         f"a non-rigid pose: max|RᵀR−I| = {ortho:.3g}, det R = {det:.4g}, "
                         f"last row {m[3].tolist()}")


def cameras_from_camdict(camdict: dict, source: str | Path = "camdict.json",
                         rigid_tol: float = RIGID_TOL) -> Cameras:
    """Cameras from a ``camdict.json`` mapping (sorted by image name); ``K`` in the files'
    pixel convention (:func:`K_from_file`).

    Each entry: ``K`` (4×4 flattened; its 3×3 block a proper intrinsic matrix), ``W2C``
    (4×4 flattened, rigid within ``rigid_tol``), optional ``dist`` ``[k1, k2, p1, p2(, k3)]``
    and ``img_size [W, H]`` (equal for all entries). Violations raise
    :class:`~eventrecon.common.errors.InputError` naming ``source`` and ``<image>.<key>``.
    """
    if not isinstance(camdict, dict) or not camdict:
        raise InputError(source, "<root>", "a non-empty JSON object of per-image entries")
    Ks, dists, c2ws, names, sizes = [], [], [], [], set()
    for name in sorted(camdict):
        entry = camdict[name]
        for key in ("K", "W2C", "img_size"):
            if key not in entry:
                raise InputError(source, f"{name}.{key}", "a value", "missing")
        try:
            K = torch.tensor(entry["K"], dtype=torch.float64)
            W2C = torch.tensor(entry["W2C"], dtype=torch.float64)
            dist = torch.tensor(entry.get("dist", [0.0] * 5), dtype=torch.float64).reshape(-1)
        except (TypeError, ValueError, RuntimeError):
            raise InputError(source, f"{name}.K/W2C/dist", "lists of numbers",
                             "something else") from None
        if K.numel() != 16 or W2C.numel() != 16:
            raise InputError(source, f"{name}.K/W2C", "16 numbers (4×4 flattened)",
                             f"{K.numel()} and {W2C.numel()}")
        if dist.numel() not in (4, 5) or not bool(torch.isfinite(dist).all()):
            raise InputError(source, f"{name}.dist", "4 or 5 finite numbers [k1 k2 p1 p2 (k3)]",
                             entry.get("dist"))
        if dist.numel() == 4:
            dist = torch.cat([dist, dist.new_zeros(1)])
        check_intrinsics(K.reshape(4, 4)[:3, :3].numpy(), source, f"{name}.K")
        check_rigid(W2C.reshape(4, 4).numpy(), source, f"{name}.W2C", rigid_tol)
        Ks.append(torch.from_numpy(K_from_file(K.reshape(4, 4)[:3, :3].numpy())))
        dists.append(dist)
        c2ws.append(torch.linalg.inv(W2C.reshape(4, 4)))
        names.append(Path(name).stem)
        sizes.add(tuple(int(s) for s in entry["img_size"]))
    if len(sizes) != 1:
        raise InputError(source, "img_size", "the same [W, H] for every view", sorted(sizes))
    (w, h), = sizes
    return Cameras(torch.stack(Ks), torch.stack(dists), torch.stack(c2ws), w, h, names)


def cameras_to_camdict(cams: Cameras, suffix: str = ".png") -> dict:
    """Inverse of :func:`cameras_from_camdict` (keys ``<name><suffix>``)."""
    out = {}
    for i, name in enumerate(cams.names):
        K4 = torch.eye(4, dtype=torch.float64)
        K4[:3, :3] = torch.from_numpy(K_to_file(cams.K[i].numpy()))
        out[f"{name}{suffix}"] = {
            "K": K4.reshape(-1).tolist(),
            "W2C": torch.linalg.inv(cams.c2w[i]).reshape(-1).tolist(),
            "dist": cams.dist[i].tolist(),
            "img_size": [cams.width, cams.height],
        }
    return out


def load_camdict(path: str | Path) -> Cameras:
    """Read a ``camdict.json`` file into :class:`Cameras` (clear error if malformed)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(path, "<file>", "an existing camdict.json", "missing") from None
    except json.JSONDecodeError as e:
        raise InputError(path, "<json>", "valid JSON", f"parse error at line {e.lineno}") from None
    return cameras_from_camdict(data, path)
