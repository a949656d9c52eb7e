"""The pixels of a camera rig rendered at any times: :class:`PixelRenderer`.

Pixels are indexed globally (``g = view·H·W + row·W + col``), each with ``s×s`` rays
(supersampling). Radiance comes from :class:`~eventrecon.sim.tracer.Renderer` (exact
ray casting, per-ray times); the hits of everything that never moves are traced once
per ray and cached. Also here: subject masks (:meth:`PixelRenderer.masks`) and the
activity of pixels over time (:meth:`PixelRenderer.activity`), which lets the event
simulator skip pixels whose radiance provably does not change.

The primitive intersections and the renderer are re-exported for callers of this module.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from eventrecon.render.cameras import Cameras
from eventrecon.sim.primitives import intersect_box, intersect_plane, intersect_sphere
from eventrecon.sim.scene import Scene
from eventrecon.sim.tracer import CHUNK as _CHUNK
from eventrecon.sim.tracer import PARTS, Hits, Renderer

__all__ = ["intersect_sphere", "intersect_box", "intersect_plane", "Hits", "Renderer",
           "PixelRenderer", "PARTS"]


class PixelRenderer:
    """The pixels of a camera set, rendered at any times (``s×s`` supersampled).

    Pixels are indexed globally, ``g = view·H·W + row·W + col``. The hits of the
    primitives that never change are traced once per ray and cached; each render then
    traces only the moving part (``Renderer.trace(part="moving")``) from them.
    """

    def __init__(self, scene: Scene, cams: Cameras, supersample: int = 1):
        self.renderer = Renderer(scene)
        self.cams, self.ss = cams, int(supersample)
        H, W, V = cams.height, cams.width, len(cams)
        off = (torch.arange(self.ss, dtype=torch.float64) + 0.5) / self.ss - 0.5
        oy, ox = torch.meshgrid(off, off, indexing="ij")
        sub = torch.stack([ox.reshape(-1), oy.reshape(-1)], -1)            # [S, 2]
        uv = (cams.pixel_grid()[:, None, :] + sub[None]).reshape(-1, 2)   # [H*W*S, 2]
        os_, ds = [], []
        for v in range(V):
            view = torch.full((uv.shape[0],), v, dtype=torch.long)
            dc = cams.pixel_directions(view, uv)
            dw = torch.einsum("ij,nj->ni", cams.c2w[v, :3, :3], dc)
            ds.append(dw / dw.norm(dim=-1, keepdim=True))
            os_.append(cams.c2w[v, :3, 3].expand_as(dw))
        S = self.ss * self.ss
        self.o = torch.cat(os_).reshape(V * H * W, S, 3)
        self.d = torch.cat(ds).reshape(V * H * W, S, 3)
        self.n_pixels = V * H * W
        self._static: Hits | None = None

    def _static_hits(self) -> Hits:
        """Hits of the static part for every ray ``[P·S]`` (traced on first use)."""
        if self._static is None:
            o, d = self.o.reshape(-1, 3), self.d.reshape(-1, 3)
            parts = [self.renderer.trace(o[i:i + _CHUNK], d[i:i + _CHUNK],
                                         torch.zeros(min(_CHUNK, o.shape[0] - i),
                                                     dtype=torch.float64), part="static")
                     for i in range(0, o.shape[0], _CHUNK)]
            self._static = Hits(*(torch.cat([getattr(h, f) for h in parts])
                                  for f in ("s", "normal", "albedo", "index")))
        return self._static

    def trace(self, pix: Tensor, t: Tensor) -> Hits:
        """Hits of the ``S`` rays of each global pixel ``pix [N]`` at times ``t [N]``
        (``[N·S]`` rows, pixel-major)."""
        if pix.shape[0] * self.ss * self.ss > _CHUNK:
            step = max(1, _CHUNK // (self.ss * self.ss))
            parts = [self.trace(pix[i:i + step], t[i:i + step])
                     for i in range(0, pix.shape[0], step)]
            return Hits(*(torch.cat([getattr(h, f) for h in parts])
                          for f in ("s", "normal", "albedo", "index")))
        S = self.ss * self.ss
        rays = (pix[:, None] * S + torch.arange(S)).reshape(-1)
        o, d = self.o.reshape(-1, 3)[rays], self.d.reshape(-1, 3)[rays]
        init = self._static_hits().take(rays) if self.renderer.has_static else None
        return self.renderer.trace(o, d, t.double().repeat_interleave(S), part="moving",
                                   init=init)

    def radiance(self, pix: Tensor, t: Tensor) -> Tensor:
        """``[N, 3]`` linear radiance of global pixels ``pix [N]`` at times ``t [N]``."""
        rgb = self.renderer.shade(self.trace(pix, t))
        return rgb.reshape(-1, self.ss * self.ss, 3).mean(1)

    def image(self, view: int, t: float) -> Tensor:
        """``[H, W, 3]`` linear radiance of one view at time ``t``."""
        return self.images(view, torch.tensor([float(t)], dtype=torch.float64))[0]

    def images(self, view: int, times: Tensor) -> Tensor:
        """``[T, H, W, 3]`` linear radiance of one view at times ``[T]`` (one batched call)."""
        H, W = self.cams.height, self.cams.width
        times = torch.as_tensor(times, dtype=torch.float64).reshape(-1)
        pix = torch.arange(view * H * W, (view + 1) * H * W).repeat(times.numel())
        return self.radiance(pix, times.repeat_interleave(H * W)).reshape(-1, H, W, 3)

    def masks(self, view: int, times: Tensor) -> Tensor:
        """``[T, H, W]`` bool subject masks of one view at times ``[T]``: a pixel is set
        when at least half of its ``s×s`` rays first hit a subject
        (:meth:`Renderer.is_subject`); with ``supersample = 1``, its centre ray."""
        H, W, S = self.cams.height, self.cams.width, self.ss * self.ss
        times = torch.as_tensor(times, dtype=torch.float64).reshape(-1)
        pix = torch.arange(view * H * W, (view + 1) * H * W).repeat(times.numel())
        hit = self.renderer.is_subject(self.trace(pix, times.repeat_interleave(H * W)))
        return (hit.reshape(-1, S).double().mean(1) >= 0.5).reshape(-1, H, W)

    def activity(self, n_intervals: int, chunk: int = 8192) -> tuple[np.ndarray, np.ndarray]:
        """Which pixels may change in which of ``n_intervals`` equal time intervals.

        A pixel is *busy* in interval ``k`` if one of its rays meets one of the interval
        spheres (:meth:`SceneObject.interval_bounds`) of a moving object that is not at
        rest over that interval; otherwise its radiance is constant over the whole
        closed interval (no shadows, static cameras). All rays of a view share its
        centre ``o``, so the test is a cone test, ``d·û ≥ √(1 − R²/D²)`` with ``û, D``
        the direction and distance of the sphere centre from ``o`` -- one matrix product
        per view over the spheres of the intervals in which something moves.

        Returns:
            ``(pix [M] int64, busy [M, K] bool)`` for the pixels busy at least once.
        """
        H, W, K = self.cams.height, self.cams.width, n_intervals
        S = self.ss * self.ss
        cen, rad, kk = [], [], []
        memos: tuple[dict, dict] = ({}, {})
        for obj in self.renderer.scene.moving:
            c, r = obj.interval_bounds(K, memos=memos)                     # [m, K, 3], [m, K]
            live = r >= 0
            cen.append(c[live])
            rad.append(r[live])
            kk.append(np.nonzero(live)[1])
        if not cen or not sum(len(k) for k in kk):
            return np.zeros(0, np.int64), np.zeros((0, K), bool)
        kk = np.concatenate(kk)
        order = np.argsort(kk, kind="stable")                      # columns grouped by k
        cen, rad, kk = np.concatenate(cen)[order], np.concatenate(rad)[order], kk[order]
        starts = np.nonzero(np.r_[True, kk[1:] != kk[:-1]])[0]
        pix_out, busy_out = [], []
        for v in range(len(self.cams)):
            u = cen - self.cams.c2w[v, :3, 3].numpy()
            D = np.linalg.norm(u, axis=1)
            U = (u / D[:, None]).T.astype(np.float32)                      # [3, C]
            lim = np.where(D > rad, np.sqrt(np.clip(1 - (rad / D) ** 2, 0, 1)), -2.0)
            lim = (lim - 1e-5).astype(np.float32)    # float32 products, conservative margin
            dirs = self.d[v * H * W:(v + 1) * H * W].numpy().astype(np.float32)  # [HW, S, 3]
            step = max(16, min(chunk, (1 << 23) // (S * U.shape[1])))     # ≤ 32 MB products
            for a in range(0, H * W, step):
                dd = dirs[a:a + step].reshape(-1, 3)
                hit = (dd @ U >= lim).reshape(-1, S, U.shape[1]).any(1)    # [rows, C]
                b = np.zeros((hit.shape[0], K), bool)
                b[:, kk[starts]] = np.logical_or.reduceat(hit, starts, axis=1)
                keep = b.any(1)
                pix_out.append(v * H * W + a + np.nonzero(keep)[0])
                busy_out.append(b[keep])
        if not pix_out:
            return np.zeros(0, np.int64), np.zeros((0, n_intervals), bool)
        return np.concatenate(pix_out).astype(np.int64), np.concatenate(busy_out)
