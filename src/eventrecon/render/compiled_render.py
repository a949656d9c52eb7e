"""Rays rendered without gradients (images, curve points): the renderer's per-ray work in
compiled loops on the CPU.

:class:`~eventrecon.render.volume.Renderer` builds every stage as PyTorch passes over
``[n, K]`` tensors: the points, the cylinder test, the kept samples gathered and their
values scattered back, both levels composited, the inverse CDF, the sort and gathers of
the union. In a 346×260 evaluation image of a fresh field those passes took ~0.25 of
~1.0 s, the field itself the rest (docs/results/history.md, "Session 59"). Here the same
stages run ray by ray, for rays that all meet the cylinder:

1. the coarse samples ``z_i`` (evaluation: no jitter) front to back in ``march_chunks``
   groups: of the rays whose transmittance ``e^{−Στ}`` is still above
   ``stop_transmittance``, the samples the occupancy grid keeps and the cylinder contains
   become rows (:func:`_select`); the field is asked on those rows (the renderer's
   ``query_field``); each ray's optical depth advances by the group's ``Σ max(σ, 0) δ``
   (:func:`_advance`);
2. :func:`_fine`: the coarse weights (the quadrature of :mod:`eventrecon.render.volume`),
   the fine samples by the deterministic inverse CDF of :func:`~.samplers.sample_pdf`
   (its quantiles ``u`` walked against the CDF, which is a merge, not a search), and the
   end of the step where ``1 − Σ w`` first falls below the stop;
3. the fine samples that the grid keeps and that lie before that point become rows and
   are asked;
4. :func:`_composite`: the union of both levels, walked as a merge of two sorted lists
   (no sort, no gather), composited in one pass.

Without skipping (``skip="none"``) every sample is asked in one group, those outside the
cylinder too (their density counts as 0), as in PyTorch's path. The field sees the same
rows in the same order as there, so its values are the same; the compositing evaluates
the same quadrature (``τ = min(max(σ, 0) max(δ, 0), 10⁴)`` in float32, the
optical depth summed in float64 as PyTorch's CPU ``cumsum`` does) one ray at a time, with
one exponential per sample: ``w_i = T_i − T_{i+1}``, ``T_i = e^{−Σ_{j<i} τ_j}`` in float64,
which is ``T_i · (−expm1(−τ_i))`` to float64 rounding. The results agree with PyTorch's
to float32 rounding (``tests/test_compiled_render.py``). Two samples at exactly the same
distance may be taken in the other order than ``torch.sort`` takes them (it is not stable).
"""

from __future__ import annotations

import itertools
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor, nn

from eventrecon.render.clipping import INSIDE_TOL
from eventrecon.render.compiled import AVAILABLE, compiled, compiled_parallel, parts, prange
from eventrecon.render.queries import query_field
from eventrecon.render.samplers import TAU_MAX, stratified

if TYPE_CHECKING:
    from eventrecon.fields.base import Field

#: :class:`eventrecon.render.volume.Renderer` (which imports this module).
Renderer = nn.Module

__all__ = ["supported", "render_final"]

#: The optical thickness clamp, in the compositing's dtype.
_TAU_MAX = np.float32(TAU_MAX)


@compiled
def _select(o: Any, d: Any, t: Any, s: Any, col0: int, col1: int, keep: Any, limit: Any,
            bounds: Any, outside: bool, base: int, pts: Any, times: Any, slot: Any) -> int:
    """Rows for the field: sample ``j ∈ [col0, col1)`` of ray ``r`` where ``keep[r, j]``
    and ``s[r, j] ≤ limit[r]``, at ``x = o + s d`` (PyTorch's rounding: the product, then
    the sum), when inside the cylinder ``x² + z² ≤ bounds[0]``,
    ``bounds[1] ≤ y ≤ bounds[2]``. Writes the rows' points ``pts [m, 3]`` and times
    ``times [m]`` in ray-major order, ``slot[r, j]`` (``base`` + the row, or −1:
    density 0) and returns ``m``. ``outside``: samples outside the cylinder get rows too,
    but slot −1 (``skip="none"`` asks every sample)."""
    m = 0
    for r in range(s.shape[0]):
        o0, o1, o2, d0, d1, d2 = o[r, 0], o[r, 1], o[r, 2], d[r, 0], d[r, 1], d[r, 2]
        for j in range(col0, col1):
            slot[r, j] = -1
            sj = s[r, j]
            if not (keep[r, j] and sj <= limit[r]):
                continue
            x, y, z = o0 + sj * d0, o1 + sj * d1, o2 + sj * d2
            inside = (x * x + z * z <= bounds[0]) and (y >= bounds[1]) and (y <= bounds[2])
            if inside or outside:
                pts[m, 0], pts[m, 1], pts[m, 2] = x, y, z
                times[m] = t[r]
                if inside:
                    slot[r, j] = base + m
                m += 1
    return m


@compiled
def _advance(s: Any, far: Any, col0: int, col1: int, slot: Any, sig: Any, base: int,
             tau: Any) -> None:
    """``tau[r] += Σ_{j ∈ [col0, col1)} max(σ_j, 0) δ_j`` over the samples with a row
    (``σ_j = sig[slot[r, j] − base]``; ``δ_j = s_{j+1} − s_j``, the last ``far − s_j``)."""
    k, zero = s.shape[1], np.float32(0)
    for r in range(s.shape[0]):
        acc = zero
        for j in range(col0, col1):
            if slot[r, j] >= 0:
                end = s[r, j + 1] if j + 1 < k else far[r]
                acc += max(sig[slot[r, j] - base], zero) * (end - s[r, j])
        tau[r] += acc


@compiled
def _fine(s: Any, far: Any, slot: Any, sig: Any, u: Any, eps: Any, stop: Any, w: Any,
          cdf: Any, s_f: Any, stop_s: Any) -> None:
    """Per ray: the coarse weights ``w [K]`` (scratch), the fine samples
    ``s_f [n, n_fine]`` at the quantiles ``u [n_fine]`` of the histogram of
    ``max(w_1 … w_{K−2}, 0) + eps`` over the midpoints of ``s`` (``cdf [K − 1]``
    scratch), and ``stop_s [n]``: the end of the first step after which ``1 − Σ w``
    is below ``stop`` (``far`` if none). ``eps``, ``stop`` are ``[1]`` float32."""
    k, zero, one = s.shape[1], np.float32(0), np.float32(1)
    m = k - 2
    tiny = np.float32(np.finfo(np.float32).tiny)
    for r in range(s.shape[0]):
        excl, trans, total = 0.0, 1.0, 0.0      # float64 running sums, as torch.cumsum
        stop_s[r] = far[r]
        found = False
        for j in range(k):
            end = s[r, j + 1] if j + 1 < k else far[r]
            sigma = max(sig[slot[r, j]], zero) if slot[r, j] >= 0 else zero
            tau = min(sigma * max(end - s[r, j], zero), _TAU_MAX)
            w[j] = zero
            if tau > zero:                      # w = T_j − T_{j+1}, both in float64
                excl += tau
                after = np.exp(-excl)
                w[j] = trans - after
                trans = after
            total += w[j]
            if not found and one - np.float32(total) < stop[0]:
                found = True
                stop_s[r] = end
        norm = 0.0
        for j in range(1, k - 1):
            norm += max(w[j], zero) + eps[0]
        norm32 = max(np.float32(norm), tiny)
        cum = 0.0
        cdf[0] = 0
        for j in range(1, m + 1):
            cum += (max(w[j], zero) + eps[0]) / norm32
            cdf[j] = cum
        cdf[m] = 1
        hi = 0
        for q in range(u.shape[0]):
            while hi <= m and cdf[hi] <= u[q]:   # searchsorted(cdf, u, right=True)
                hi += 1
            b = min(max(hi, 1), m)
            lo_s = np.float32(0.5) * (s[r, b - 1] + s[r, b])      # the bins' edges
            hi_s = np.float32(0.5) * (s[r, b] + s[r, b + 1])
            denom = cdf[b] - cdf[b - 1]
            frac = min(max((u[q] - cdf[b - 1]) / (denom if denom > 0 else one), zero), one)
            s_f[r, q] = lo_s + frac * (hi_s - lo_s)


@compiled
def _composite(s_c: Any, slot_c: Any, s_f: Any, slot_f: Any, sig: Any, col: Any, far: Any,
               bg: Any, ends: Any, end_rows: Any, merged: Any, rows: Any, rgb: Any,
               opacity: Any, depth: Any) -> None:
    """The union of the coarse ``s_c [n, K_c]`` and fine ``s_f [n, K_f]`` samples (each
    sorted) in order, composited over ``bg [n, 3]``: ``rgb [n, 3]`` (clamped to [0, 1]),
    ``opacity [n]``, ``depth [n]`` (:func:`eventrecon.render.volume.composite`). A sample's
    values are row ``slot`` of ``sig [M]``, ``col [M, 3]`` (density 0 where ``slot`` is
    −1). Scratch: ``ends, end_rows [K_c + K_f + 2]`` (each list with an infinite last
    sample, so that the merge needs no branch) and ``merged, rows [K_c + K_f]``."""
    kc, kf, zero, one = s_c.shape[1], s_f.shape[1], np.float32(0), np.float32(1)
    k = kc + kf
    for r in range(s_c.shape[0]):
        for q in range(kc):
            ends[q], end_rows[q] = s_c[r, q], slot_c[r, q]
        for q in range(kf):
            ends[kc + 1 + q], end_rows[kc + 1 + q] = s_f[r, q], slot_f[r, q]
        ends[kc], ends[k + 1] = np.inf, np.inf
        i, j = 0, kc + 1
        for q in range(k):                      # the merge (ties: the coarse sample first)
            coarse = ends[i] <= ends[j]
            merged[q] = ends[i] if coarse else ends[j]
            rows[q] = end_rows[i] if coarse else end_rows[j]
            i += coarse
            j += 1 - coarse
        excl, trans, c0, c1, c2, dep = 0.0, 1.0, 0.0, 0.0, 0.0, 0.0     # float64 sums
        for q in range(k):
            row = rows[q]
            if row < 0:
                continue
            end = merged[q + 1] if q + 1 < k else far[r]
            tau = min(max(sig[row], zero) * max(end - merged[q], zero), _TAU_MAX)
            if tau > zero:                      # w = T_q − T_{q+1}, both in float64
                excl += tau
                after = np.exp(-excl)
                wt = np.float32(trans - after)
                trans = after
                c0 += wt * col[row, 0]
                c1 += wt * col[row, 1]
                c2 += wt * col[row, 2]
                dep += wt * merged[q]
        t_last = np.float32(trans)
        rgb[r, 0] = min(max(np.float32(c0) + t_last * bg[r, 0], zero), one)
        rgb[r, 1] = min(max(np.float32(c1) + t_last * bg[r, 1], zero), one)
        rgb[r, 2] = min(max(np.float32(c2) + t_last * bg[r, 2], zero), one)
        opacity[r] = one - t_last
        depth[r] = np.float32(dep) + t_last * far[r]


@compiled_parallel
def _fine_parts(s: Any, far: Any, slot: Any, sig: Any, u: Any, eps: Any, stop: Any, w: Any,
                cdf: Any, s_f: Any, stop_s: Any) -> None:
    """:func:`_fine` on ``P`` equal ranges of the rays at once (``w [P, K]``,
    ``cdf [P, K − 1]``: each range's scratch)."""
    n, p = s.shape[0], w.shape[0]
    for k in prange(p):
        a, b = n * k // p, n * (k + 1) // p
        _fine(s[a:b], far[a:b], slot[a:b], sig, u, eps, stop, w[k], cdf[k], s_f[a:b],
              stop_s[a:b])


@compiled_parallel
def _composite_parts(s_c: Any, slot_c: Any, s_f: Any, slot_f: Any, sig: Any, col: Any,
                     far: Any, bg: Any, ends: Any, end_rows: Any, merged: Any, rows: Any,
                     rgb: Any, opacity: Any, depth: Any) -> None:
    """:func:`_composite` on ``P`` equal ranges of the rays at once (``ends, end_rows
    [P, K_c + K_f + 2]``, ``merged, rows [P, K_c + K_f]``: each range's scratch)."""
    n, p = s_c.shape[0], merged.shape[0]
    for k in prange(p):
        a, b = n * k // p, n * (k + 1) // p
        _composite(s_c[a:b], slot_c[a:b], s_f[a:b], slot_f[a:b], sig, col, far[a:b],
                   bg[a:b], ends[k], end_rows[k], merged[k], rows[k], rgb[a:b],
                   opacity[a:b], depth[a:b])


#: Rays per range, at least, when the loops are split between threads.
_GRAIN = 1024


def supported(field: Field, o: Tensor, d: Tensor, t: Tensor, bg: Tensor) -> bool:
    """Whether :func:`render_final` serves this call: numba, no autograd, float32 rays
    ``o, d [N, 3]``, ``t [N, 1]``, ``bg [N, 3]`` and the field on the CPU."""
    state = itertools.chain(field.parameters(), field.buffers())
    return (AVAILABLE and not torch.is_grad_enabled()
            and all(x.device.type == "cpu" and x.dtype == torch.float32
                    for x in (o, d, t, bg))
            and all(p.device.type == "cpu" for p in itertools.islice(state, 1))
            and o.dim() == 2 and o.shape[1:] == (3,) and d.shape == o.shape
            and t.shape == (o.shape[0], 1) and bg.shape == o.shape)


class _Rows:
    """The field's values at the samples of one call's rays, asked group by group
    (:func:`_select`), kept as the rows ``σ [M]``, ``rgb [M, 3]`` float32 of all groups."""

    def __init__(self, renderer: Renderer, field: Field, o: Tensor, d: Tensor,
                 t: Tensor) -> None:
        self.renderer, self.field = renderer, field
        self.o, self.d, self.t = (x.contiguous().numpy() for x in (o, d, t[:, 0]))
        cyl, radius = renderer.cylinder, renderer.cylinder.radius * renderer.clip_scale
        self.bounds = np.array([(radius + INSIDE_TOL) ** 2 if radius > 0 else -1.0,
                                cyl.y_min - INSIDE_TOL, cyl.y_max + INSIDE_TOL], np.float32)
        self.sig: list[np.ndarray] = []
        self.rgb: list[np.ndarray] = []
        self.count = 0

    def ask(self, s: np.ndarray, cols: tuple[int, int], keep: np.ndarray, limit: np.ndarray,
            slot: np.ndarray, outside: bool) -> np.ndarray:
        """Ask the field at the selected samples of columns ``cols`` of ``s [n, K]``
        (``slot`` filled for those columns, rows numbered after the earlier groups');
        returns this group's ``σ [m]``."""
        size = s.shape[0] * (cols[1] - cols[0])
        pts, times = np.empty((size, 3), np.float32), np.empty((size, 1), np.float32)
        m = _select(self.o, self.d, self.t, s, cols[0], cols[1], keep, limit, self.bounds,
                    outside, self.count, pts, times, slot)
        self.renderer.field_inputs += m
        self.count += m
        if m == 0:
            return np.zeros(0, np.float32)
        r = self.renderer
        sigma, rgb = query_field(self.field, torch.from_numpy(pts[:m]),
                                 torch.from_numpy(times[:m]), r.query_buckets, r.query_rows)
        self.sig.append(sigma.float().contiguous().numpy())
        self.rgb.append(rgb.float().contiguous().numpy())
        return self.sig[-1]

    def values(self) -> tuple[np.ndarray, np.ndarray]:
        """``σ [M]``, ``rgb [M, 3]``: every row asked so far."""
        if not self.sig:
            return np.zeros(0, np.float32), np.zeros((0, 3), np.float32)
        return np.concatenate(self.sig), np.concatenate(self.rgb)


def _render_hit(renderer: Renderer, field: Field, o: Tensor, d: Tensor, t: Tensor,
                bg: Tensor, near: Tensor, far: Tensor) -> dict[str, Tensor]:
    """Both levels of rays that all meet the cylinder (module docstring); the final
    level's ``rgb [n, 3]``, ``opacity [n]``, ``depth [n]``."""
    r, n, k = renderer, o.shape[0], renderer.n_coarse
    skipping = r.skipping
    rows = _Rows(r, field, o, d, t)
    s_c = stratified(near, far, k, perturb=False).contiguous()
    sc, far_np = s_c.numpy(), far.contiguous().numpy()
    slot_c = np.empty((n, k), np.int64)
    keep = r._occupied(o, d, t, s_c).numpy() if skipping else np.ones((n, k), np.bool_)
    bounds = torch.linspace(0, k, r.march_chunks + 1).round().long().tolist()
    groups = ([(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a] if skipping
              else [(0, k)])
    tau = torch.zeros(n)
    for a, b in groups:          # a ray that stopped asks nothing more (limit −inf)
        limit = torch.where(torch.exp(-tau) > r.stop_transmittance, np.inf, -np.inf)
        sig = rows.ask(sc, (a, b), keep, limit.numpy(), slot_c, not skipping)
        _advance(sc, far_np, a, b, slot_c, sig, rows.count - sig.shape[0], tau.numpy())
    s_f = np.empty((n, r.n_fine), np.float32)
    slot_f = np.full((n, r.n_fine), -1, np.int64)
    if r.n_fine:
        stop_s = np.empty(n, np.float32)
        p = parts(n, _GRAIN)
        _fine_parts(sc, far_np, slot_c, rows.values()[0],
                    torch.linspace(0.0, 1.0, r.n_fine).numpy(), np.array([1e-6], np.float32),
                    np.array([r.stop_transmittance if skipping else -1.0], np.float32),
                    np.empty((p, k), np.float32), np.empty((p, k - 1), np.float32), s_f, stop_s)
        if skipping:
            keep_f = r._occupied(o, d, t, torch.from_numpy(s_f)).numpy()
        else:
            keep_f, stop_s[:] = np.ones((n, r.n_fine), np.bool_), np.inf
        rows.ask(s_f, (0, r.n_fine), keep_f, stop_s, slot_f, not skipping)
    sig_all, rgb_all = rows.values()
    out = {"rgb": torch.empty(n, 3), "opacity": torch.empty(n), "depth": torch.empty(n)}
    p, union = parts(n, _GRAIN), k + r.n_fine
    _composite_parts(sc, slot_c, s_f, slot_f, sig_all, rgb_all, far_np, bg.contiguous().numpy(),
                     np.empty((p, union + 2), np.float32), np.empty((p, union + 2), np.int64),
                     np.empty((p, union), np.float32), np.empty((p, union), np.int64),
                     out["rgb"].numpy(), out["opacity"].numpy(), out["depth"].numpy())
    return out


def render_final(renderer: Renderer, field: Field, o: Tensor, d: Tensor, t: Tensor,
                 bg: Tensor) -> dict[str, Tensor] | None:
    """The final level of :meth:`Renderer.forward` without jitter: ``rgb [N, 3]``,
    ``opacity [N]``, ``depth [N]`` (for rays that miss the cylinder the background, 0 and
    0); ``None`` where not :func:`supported`."""
    if not supported(field, o, d, t, bg):
        return None
    near, far, hit = renderer.cylinder.ray_interval(o, d)
    idx = hit.nonzero().squeeze(1)
    if idx.numel() == o.shape[0]:
        return _render_hit(renderer, field, o, d, t, bg, near, far)
    out = {"rgb": bg.clone(), "opacity": torch.zeros(o.shape[0]), "depth": far.clone()}
    if idx.numel():
        sub = _render_hit(renderer, field, o[idx], d[idx], t[idx], bg[idx], near[idx],
                          far[idx])
        for key, value in sub.items():
            out[key][idx] = value
    return out
