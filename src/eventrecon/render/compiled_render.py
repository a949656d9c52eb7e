"""The renderer's two levels in compiled loops on the CPU, for training and images.

:meth:`~eventrecon.render.volume.Renderer.forward` builds every stage as PyTorch passes
over ``[n, K]`` tensors: the points, the cylinder test, the kept samples gathered and
their values scattered back, both levels composited, the inverse CDF, the sort and the
gathers of the union, and autograd's passes back through them. Here, for rays that all
meet the cylinder, the same stages run ray by ray (:func:`render_hit`):

1. the coarse samples (:func:`~.samplers.stratified`, the same draws) that the occupancy
   grid keeps and the cylinder contains become rows for the field (:func:`_select`);
   the field is asked on them with the renderer's ``query_field``;
2. with skipping, the coarse samples are marched front to back in ``march_chunks``
   groups: a ray whose transmittance ``e^{−Σ max(σ, 0) δ}`` is below
   ``stop_transmittance`` at a group's start takes no more samples (:func:`_advance`).
   Without gradients each group is asked only for the rays still alive; with gradients
   the field is asked once and the stopped samples are masked (they count as ``σ · 0``,
   so only a NaN there shows), as :meth:`Renderer._march` multiplies by its masks;
3. the coarse level is composited from the rows (:mod:`eventrecon.render.composite_rows`);
4. :func:`_fine`: the fine samples by the inverse CDF of :func:`~.samplers.sample_pdf`
   (the same quantiles or the same uniform draws, sorted by a network,
   :mod:`~eventrecon.render.sort_rows`, and walked against the CDF: a merge, not a
   search) and the end of the step where ``1 − Σ w`` first falls below the stop;
   the fine samples the grid keeps before that point are asked;
5. the union of both levels, merged as two sorted lists, is composited.

Without skipping (``skip="none"``) every sample is asked, those outside the cylinder too
(masked: ``σ · 0``), as in PyTorch's path. The coarse level asks the field on the same
rows in the same order, so its values are the same; the compositing agrees with PyTorch's
to float32 rounding, forward and backward (``tests/test_compiled_render.py``). The fine
samples agree to rounding too, except in histogram bins that hold almost nothing, where
the inverse CDF divides by a difference of nearly equal CDF values (the normaliser is
summed in float64 here, in float32 there): such a sample may move by up to ~1e-3 of a
distance, and a sample right at a stop or a cell boundary may be asked in one path and not
the other. A gradient of the weights, or a second derivative, needs PyTorch's passes.
"""

from __future__ import annotations

import itertools
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor, nn

from eventrecon.render.clipping import INSIDE_TOL
from eventrecon.render.compiled import AVAILABLE, compiled, compiled_parallel, parts, prange
from eventrecon.render.composite_rows import RAYS_PER_RANGE, composite_rows, merge
from eventrecon.render.queries import query_field
from eventrecon.render.samplers import stratified, uniform
from eventrecon.render.sort_rows import sort_rows

if TYPE_CHECKING:
    from eventrecon.fields.base import Field

__all__ = ["supported", "render_hit"]

@compiled
def _select(o: Any, d: Any, t: Any, s: Any, col0: int, col1: int, keep: Any, limit: Any,
            bounds: Any, outside: bool, base: int, pts: Any, times: Any, slot: Any) -> int:
    """Rows for the field: sample ``j ∈ [col0, col1)`` of ray ``r`` where ``keep[r, j]``
    and ``s[r, j] ≤ limit[r]``, at ``x = o + s d`` (PyTorch's rounding: the product, then
    the sum), when inside the cylinder ``x² + z² ≤ bounds[0]``,
    ``bounds[1] ≤ y ≤ bounds[2]``. Writes the rows' points ``pts [m, 3]`` and times
    ``times [m]`` in ray-major order, ``slot[r, j]`` (``base`` + the row, or −1:
    density 0) and returns ``m``. ``outside``: samples outside the cylinder get rows too,
    masked (``slot = −(base + row) − 2``: they count as ``σ · 0``; ``skip="none"`` asks
    every sample)."""
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
                slot[r, j] = base + m if inside else -(base + m) - 2
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
                sigma = sig[slot[r, j] - base]          # clamped at 0, a NaN kept
                acc += (zero if sigma < zero else sigma) * (end - s[r, j])
        tau[r] += acc


@compiled
def _fine(s: Any, far: Any, weights: Any, u: Any, eps: Any, stop: Any, cdf: Any, s_f: Any,
          stop_s: Any) -> None:
    """Per ray: the fine samples ``s_f [n, n_fine]`` at the quantiles ``u [n, n_fine]``
    (sorted per ray) of the histogram of ``max(w_1 … w_{K−2}, 0) + eps`` over the
    midpoints of ``s [n, K]`` (``weights [n, K]``; ``cdf [K − 1]`` scratch), and
    ``stop_s [n]``: the end of the first step after which ``1 − Σ w`` is below ``stop``
    (``far`` if none). ``eps``, ``stop`` are ``[1]`` float32."""
    k, zero, one = s.shape[1], np.float32(0), np.float32(1)
    m = k - 2
    tiny = np.float32(np.finfo(np.float32).tiny)
    for r in range(s.shape[0]):
        stop_s[r] = far[r]
        total = 0.0                              # float64 running sums, as torch.cumsum
        for j in range(k):
            total += weights[r, j]
            if one - np.float32(total) < stop[0]:
                stop_s[r] = s[r, j + 1] if j + 1 < k else far[r]
                break
        norm = 0.0
        for j in range(1, k - 1):
            norm += max(weights[r, j], zero) + eps[0]
        norm32 = max(np.float32(norm), tiny)
        cum = 0.0
        cdf[0] = 0
        for j in range(1, m + 1):
            cum += (max(weights[r, j], zero) + eps[0]) / norm32
            cdf[j] = cum
        cdf[m] = 1
        hi = 0
        for q in range(u.shape[1]):
            while hi <= m and cdf[hi] <= u[r, q]:   # searchsorted(cdf, u, right=True)
                hi += 1
            b = min(max(hi, 1), m)
            lo_s = np.float32(0.5) * (s[r, b - 1] + s[r, b])      # the bins' edges
            hi_s = np.float32(0.5) * (s[r, b] + s[r, b + 1])
            denom = cdf[b] - cdf[b - 1]
            frac = min(max((u[r, q] - cdf[b - 1]) / (denom if denom > 0 else one), zero), one)
            s_f[r, q] = lo_s + frac * (hi_s - lo_s)


@compiled_parallel
def _fine_parts(s: Any, far: Any, weights: Any, u: Any, eps: Any, stop: Any, cdf: Any,
                s_f: Any, stop_s: Any) -> None:
    """:func:`_fine` on ``P`` equal ranges of the rays at once (``cdf [P, K − 1]``: each
    range's scratch)."""
    n, p = s.shape[0], cdf.shape[0]
    for part in prange(p):
        a, b = n * part // p, n * (part + 1) // p
        _fine(s[a:b], far[a:b], weights[a:b], u[a:b], eps, stop, cdf[part], s_f[a:b],
              stop_s[a:b])


def supported(field: Field, o: Tensor, d: Tensor, t: Tensor, bg: Tensor) -> bool:
    """Whether :func:`render_hit` serves this call: numba, float32 rays ``o, d [N, 3]``,
    ``t [N, 1]``, ``bg [N, 3]`` and the field on the CPU, and no gradient asked of the
    rays or the background (only the field's rows carry one here)."""
    state = itertools.chain(field.parameters(), field.buffers())
    rays = (o, d, t, bg)
    return (AVAILABLE and all(x.device.type == "cpu" and x.dtype == torch.float32
                              for x in rays)
            and not (torch.is_grad_enabled() and any(x.requires_grad for x in rays))
            and all(p.device.type == "cpu" for p in itertools.islice(state, 1))
            and o.dim() == 2 and o.shape[1:] == (3,) and d.shape == o.shape
            and t.shape == (o.shape[0], 1) and bg.shape == o.shape)


class _Rows:
    """The field's answers at the samples of one call's rays, asked level by level or
    group by group (:func:`_select`), kept as rows ``σ [M]``, ``rgb [M, 3]`` float32
    (with autograd's graph when gradients are on)."""

    def __init__(self, renderer: nn.Module, field: Field, o: Tensor, d: Tensor,
                 t: Tensor) -> None:
        self.renderer, self.field = renderer, field
        self.o, self.d, self.t = (x.contiguous().numpy() for x in (o, d, t[:, 0]))
        cyl, radius = renderer.cylinder, renderer.cylinder.radius * renderer.clip_scale
        self.bounds = np.array([(radius + INSIDE_TOL) ** 2 if radius > 0 else -1.0,
                                cyl.y_min - INSIDE_TOL, cyl.y_max + INSIDE_TOL], np.float32)
        self.sig: list[Tensor] = []
        self.rgb: list[Tensor] = []
        self.count = 0

    def ask(self, s: np.ndarray, cols: tuple[int, int], keep: np.ndarray, limit: np.ndarray,
            slot: np.ndarray, outside: bool) -> np.ndarray:
        """Ask the field at the selected samples of columns ``cols`` of ``s [n, K]``
        (``slot`` filled for those columns, rows numbered after the earlier asks');
        returns these rows' ``σ [m]`` (detached)."""
        size = s.shape[0] * (cols[1] - cols[0])
        pts, times = np.empty((size, 3), np.float32), np.empty((size, 1), np.float32)
        m = _select(self.o, self.d, self.t, s, cols[0], cols[1], keep, limit, self.bounds,
                    outside, self.count, pts, times, slot)
        self.renderer.field_inputs += m
        self.count += m
        if m == 0 and not torch.is_grad_enabled():   # with autograd the field is asked on
            return np.zeros(0, np.float32)           # no rows: the outputs stay connected
        r = self.renderer
        sigma, rgb = query_field(self.field, torch.from_numpy(pts[:m]),
                                 torch.from_numpy(times[:m]), r.query_buckets, r.query_rows)
        self.sig.append(sigma.float())
        self.rgb.append(rgb.float())
        return self.sig[-1].detach().contiguous().numpy()

    def values(self) -> tuple[Tensor, Tensor]:
        """``σ [M]``, ``rgb [M, 3]``: every row asked so far."""
        if not self.sig:
            return torch.zeros(0), torch.zeros(0, 3)
        if len(self.sig) == 1:
            return self.sig[0], self.rgb[0]
        return torch.cat(self.sig), torch.cat(self.rgb)


def _coarse(renderer: nn.Module, rows: _Rows, s_c: Tensor, far: np.ndarray,
            keep: np.ndarray) -> np.ndarray:
    """Ask the coarse samples (module docstring, steps 1–2); returns ``slot [n, K]``."""
    r, (n, k) = renderer, s_c.shape
    sc, slot = s_c.numpy(), np.empty((n, k), np.int64)
    if not r.skipping:
        rows.ask(sc, (0, k), keep, np.full(n, np.inf, np.float32), slot, True)
        return slot
    groups, tau = r.march_groups(k), torch.zeros(n)
    if torch.is_grad_enabled():   # one call; the stopped samples are masked (σ · 0)
        sig = rows.ask(sc, (0, k), keep, np.full(n, np.inf, np.float32), slot, False)
        for a, b in groups:
            stopped = (torch.exp(-tau) > r.stop_transmittance).logical_not().numpy()
            cols = slot[stopped, a:b]
            slot[stopped, a:b] = np.where(cols >= 0, -cols - 2, cols)
            _advance(sc, far, a, b, slot, sig, 0, tau.numpy())
        return slot
    for a, b in groups:           # a ray that stopped asks nothing more (limit −inf)
        limit = torch.where(torch.exp(-tau) > r.stop_transmittance, np.inf, -np.inf)
        sig = rows.ask(sc, (a, b), keep, limit.numpy(), slot, False)
        _advance(sc, far, a, b, slot, sig, rows.count - sig.shape[0], tau.numpy())
    return slot


def render_hit(renderer: nn.Module, field: Field, o: Tensor, d: Tensor, t: Tensor,
               bg: Tensor, near: Tensor, far: Tensor, perturb: bool,
               gen: torch.Generator | None, copies: int) -> list[dict[str, Tensor]]:
    """:meth:`Renderer._render_hit` (its arguments and levels) in compiled loops, for
    rays that all meet the cylinder (module docstring)."""
    r, n, k = renderer, o.shape[0], renderer.n_coarse
    skipping = r.skipping
    rows = _Rows(r, field, o, d, t)
    s_c = stratified(near, far, k, perturb, gen, copies).contiguous()
    far, bg = far.contiguous(), bg.contiguous()
    keep = r._occupied(o, d, t, s_c).numpy() if skipping else np.ones((n, k), np.bool_)
    slot_c = _coarse(r, rows, s_c, far.numpy(), keep)
    levels = [composite_rows(*rows.values(), s_c, torch.from_numpy(slot_c), far, bg)]
    if r.n_fine == 0:
        return levels
    if perturb:                   # sample_pdf's draws, in the same order
        u = sort_rows(uniform((n, r.n_fine), gen, s_c))
    else:
        u = torch.linspace(0.0, 1.0, r.n_fine).expand(n, r.n_fine).contiguous()
    s_f, stop_s = torch.empty(n, r.n_fine), np.empty(n, np.float32)
    _fine_parts(s_c.numpy(), far.numpy(), levels[0]["weights"].numpy(), u.numpy(),
                np.array([1e-6], np.float32),
                np.array([r.stop_transmittance if skipping else -1.0], np.float32),
                np.empty((parts(n, RAYS_PER_RANGE), k - 1), np.float32), s_f.numpy(), stop_s)
    slot_f = np.empty((n, r.n_fine), np.int64)
    if skipping:
        rows.ask(s_f.numpy(), (0, r.n_fine), r._occupied(o, d, t, s_f).numpy(), stop_s,
                 slot_f, False)
    else:
        rows.ask(s_f.numpy(), (0, r.n_fine), np.ones((n, r.n_fine), np.bool_),
                 np.full(n, np.inf, np.float32), slot_f, True)
    s_u, slot_u = merge(s_c, torch.from_numpy(slot_c), s_f, torch.from_numpy(slot_f))
    levels.append(composite_rows(*rows.values(), s_u, slot_u, far, bg))
    return levels
