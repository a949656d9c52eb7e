"""Alpha compositing from the field's rows, forward and backward, in compiled loops (CPU).

The renderer's compiled path (:mod:`eventrecon.render.compiled_render`) asks the field
only at the samples that count and keeps its answers as rows ``σ [M]``, ``c [M, 3]``; a
map ``slot [n, K]`` says which row sample ``i`` of ray ``r`` reads: ``slot ≥ 0``, the row;
−1, density 0 (not asked); ``slot ≤ −2``, row ``−slot − 2`` was asked but is masked (a
stopped sample, or one outside the cylinder): it counts as ``σ · 0``, ``c · 0``, so it adds
nothing unless the field returned a NaN or an infinity there, which makes the ray NaN, as
PyTorch's masks do (``0 · NaN``), and gets no gradient. :class:`CompositeRows`
composites the sorted samples ``s [n, K]`` of each ray over its background with the
quadrature of :mod:`eventrecon.render.volume`,

.. math::
    \\tau_i = \\min(\\max(\\sigma_i, 0)\\max(\\delta_i, 0), \\tau_{max}),\\quad
    T_i = e^{-\\sum_{j<i}\\tau_j},\\quad w_i = T_i - T_{i+1} = T_i\\,(1 - e^{-\\tau_i}),

    C = \\mathrm{clamp}\\Big(\\sum_i w_i c_i + T_K\\,bg, 0, 1\\Big),\\quad O = 1 - T_K,\\quad
    D = \\sum_i w_i s_i + T_K\\,far,

the optical depth summed and ``T`` evaluated in float64, one exponential per sample: the
same values as PyTorch's float32 ``exp(−Σ) · (−expm1(−τ))`` to float32 rounding, except
the weights of steps with ``τ`` below ~1e-9, whose relative error grows as ``1e-16 / τ``
(their absolute error stays below 1e-15). When ``σ`` or ``c`` need a gradient, the
forward pass keeps each ray's ``T`` and ``Σ w c`` (float64 ``[n, K]`` and ``[n, 3]``) so
that the backward pass need not evaluate them again. The gradient comes from one pass
per ray from the back, with ``g_C`` (zero where the clamp is active), ``g_O``, ``g_D``
the incoming gradients:

.. math::
    \\frac{\\partial L}{\\partial c_i} = w_i\\,g_C,\\qquad
    \\frac{\\partial L}{\\partial \\tau_i} = g_C\\cdot\\Big(T_{i+1} c_i - \\sum_{j>i} w_j c_j
    - T_K\\,bg\\Big) + g_O T_K + g_D\\Big(T_{i+1} s_i - \\sum_{j>i} w_j s_j - T_K\\,far\\Big),

and :math:`\\partial L/\\partial\\sigma_i = \\partial L/\\partial\\tau_i \\cdot \\max(\\delta_i, 0)`
where ``σ_i ≥ 0`` and ``τ`` is not clamped (PyTorch's clamps pass the gradient at their
bounds). The weights ``w [n, K]`` are returned too, without gradient (the fine level's
histogram; a loss on them would need PyTorch's passes, ``render.compiled=false``), and the
backward pass is not itself differentiable. :func:`merge` forms the union of two sorted
sample lists with their slots.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from eventrecon.render.compiled import compiled, compiled_parallel, parts, prange
from eventrecon.render.samplers import TAU_MAX

__all__ = ["CompositeRows", "composite_rows", "merge", "RAYS_PER_RANGE"]

#: Rays per range, at least, when a loop is split between threads.
RAYS_PER_RANGE = 1024


@compiled
def _tau(sigma: Any, step: Any, tau_max: Any) -> Any:
    """``τ = min(max(σ, 0) · max(δ, 0), τ_max)`` in float32, a NaN kept (PyTorch's clamps
    propagate it, and a diverging run must see it). ``tau_max`` is an argument, not a
    global: numba's cache would keep a global's old value after an edit of
    :data:`~eventrecon.render.samplers.TAU_MAX`."""
    zero = np.float32(0)
    raw = (zero if sigma < zero else sigma) * (zero if step < zero else step)
    return tau_max if raw > tau_max else raw


@compiled
def _read(slot: Any, sig: Any, col: Any, zero: Any) -> tuple:
    """``(σ, c0, c1, c2)`` of a sample with ``slot ≠ −1``: its row's, or for a masked
    row (``slot ≤ −2``) those times 0 (0 unless non-finite)."""
    if slot >= 0:
        return sig[slot], col[slot, 0], col[slot, 1], col[slot, 2]
    row = -slot - 2
    return sig[row] * zero, col[row, 0] * zero, col[row, 1] * zero, col[row, 2] * zero


@compiled
def _unit(x: Any) -> Any:
    """``x`` clamped to [0, 1], a NaN kept."""
    return np.float32(0) if x < 0 else (np.float32(1) if x > 1 else x)


@compiled
def _ray(s: Any, slot: Any, far: Any, sig: Any, col: Any, tau_max: Any, r: int,
         after: Any) -> tuple:
    """Ray ``r`` front to back: ``after[q] = T_{q+1}`` (float64) and the float64 sums
    ``(Σ w c₀, Σ w c₁, Σ w c₂, Σ w s)`` with ``w = float32(T_q − T_{q+1})``. A sample with
    a row adds ``w c`` even at ``w = 0``, so a non-finite colour or density makes the ray
    NaN, as in PyTorch's compositing."""
    k, zero = s.shape[1], np.float32(0)
    excl, trans, c0, c1, c2, dep = 0.0, 1.0, 0.0, 0.0, 0.0, 0.0     # float64 sums
    for q in range(k):
        if slot[r, q] != -1:
            sigma, x0, x1, x2 = _read(slot[r, q], sig, col, zero)
            end = s[r, q + 1] if q + 1 < k else far[r]
            tau = _tau(sigma, end - s[r, q], tau_max)
            wt = zero
            if tau != zero:                     # w = T_q − T_{q+1}, both in float64
                excl += tau
                before, trans = trans, np.exp(-excl)
                wt = np.float32(before - trans)
            c0 += wt * x0
            c1 += wt * x1
            c2 += wt * x2
            dep += wt * s[r, q]
        after[q] = trans
    return c0, c1, c2, dep


@compiled
def _forward(s: Any, slot: Any, far: Any, sig: Any, col: Any, bg: Any, tau_max: Any,
             rgb: Any, opacity: Any, depth: Any, weights: Any, after: Any,
             sums: Any) -> None:
    """``rgb [n, 3]``, ``opacity [n]``, ``depth [n]`` and ``weights [n, K]`` of the rays
    (module docstring); ``s [n, K]`` sorted, ``slot [n, K]`` rows of ``sig [M]``,
    ``col [M, 3]``. ``after``, ``sums``: float64, either ``[n, K]`` and ``[n, 3]``, where
    each ray's transmittances (:func:`_ray`) and colour sums are kept for the backward
    pass, or ``[1, K]`` and ``[1, 3]`` scratch."""
    k, one, keep = s.shape[1], np.float32(1), after.shape[0] > 1
    for r in range(s.shape[0]):
        i = r if keep else 0
        c0, c1, c2, dep = _ray(s, slot, far, sig, col, tau_max, r, after[i])
        sums[i, 0], sums[i, 1], sums[i, 2] = c0, c1, c2
        after_r = after[i]
        before = 1.0
        for q in range(k):
            weights[r, q] = np.float32(before - after_r[q])
            before = after_r[q]
        t_last = np.float32(after_r[k - 1])
        rgb[r, 0] = _unit(np.float32(c0) + t_last * bg[r, 0])
        rgb[r, 1] = _unit(np.float32(c1) + t_last * bg[r, 1])
        rgb[r, 2] = _unit(np.float32(c2) + t_last * bg[r, 2])
        opacity[r] = one - t_last
        depth[r] = np.float32(dep) + t_last * far[r]


@compiled
def _backward(s: Any, slot: Any, far: Any, sig: Any, col: Any, bg: Any, tau_max: Any,
              g_rgb: Any, g_opacity: Any, g_depth: Any, g_sig: Any, g_col: Any,
              after_all: Any, sums: Any) -> None:
    """``g_sig [M]``, ``g_col [M, 3]`` (zero on entry; masked rows keep 0) from the
    outputs' gradients (module docstring); ``after_all [n, K]``, ``sums [n, 3]``: the
    forward pass's transmittances and colour sums (:func:`_forward`)."""
    k, zero, one = s.shape[1], np.float32(0), np.float32(1)
    for r in range(s.shape[0]):
        after = after_all[r]
        c0, c1, c2 = sums[r, 0], sums[r, 1], sums[r, 2]
        t_last = np.float32(after[k - 1])
        # the clamp of C to [0, 1] passes the gradient where C is inside, bounds included
        pre = (np.float32(c0) + t_last * bg[r, 0], np.float32(c1) + t_last * bg[r, 1],
               np.float32(c2) + t_last * bg[r, 2])
        g0 = g_rgb[r, 0] if zero <= pre[0] <= one else zero
        g1 = g_rgb[r, 1] if zero <= pre[1] <= one else zero
        g2 = g_rgb[r, 2] if zero <= pre[2] <= one else zero
        t_k = after[k - 1]
        b0, b1, b2 = t_k * bg[r, 0], t_k * bg[r, 1], t_k * bg[r, 2]     # Σ_{j>i} w c + T_K bg
        bd = t_k * far[r]                                               # Σ_{j>i} w s + T_K far
        g_o, g_d = np.float64(g_opacity[r]), np.float64(g_depth[r])
        for q in range(k - 1, -1, -1):
            row = slot[r, q]
            if row < 0:                         # no row, or masked: no gradient, and
                continue                        # (finite there) no weight
            t_next = after[q]
            wt = (after[q - 1] if q > 0 else 1.0) - t_next
            end = s[r, q + 1] if q + 1 < k else far[r]
            step = max(end - s[r, q], zero)
            x0, x1, x2, sq = col[row, 0], col[row, 1], col[row, 2], s[r, q]
            d_tau = (g0 * (t_next * x0 - b0) + g1 * (t_next * x1 - b1)
                     + g2 * (t_next * x2 - b2) + g_o * t_k + g_d * (t_next * sq - bd))
            passes = sig[row] >= zero and max(sig[row], zero) * step <= tau_max
            g_sig[row] = np.float32(d_tau * step) if passes else zero
            g_col[row, 0] = np.float32(wt * g0)
            g_col[row, 1] = np.float32(wt * g1)
            g_col[row, 2] = np.float32(wt * g2)
            b0 += wt * x0
            b1 += wt * x1
            b2 += wt * x2
            bd += wt * sq


@compiled_parallel
def _forward_parts(s: Any, slot: Any, far: Any, sig: Any, col: Any, bg: Any, tau_max: Any,
                   rgb: Any, opacity: Any, depth: Any, weights: Any, after: Any,
                   sums: Any, p: int, keep: bool) -> None:
    """:func:`_forward` on ``p`` equal ranges of the rays at once (``keep``: ``after
    [n, K]``, ``sums [n, 3]`` kept; otherwise ``[p, K]``, ``[p, 3]``, each range's
    scratch)."""
    n = s.shape[0]
    for part in prange(p):
        a, b = n * part // p, n * (part + 1) // p
        lo, hi = (a, b) if keep else (part, part + 1)
        _forward(s[a:b], slot[a:b], far[a:b], sig, col, bg[a:b], tau_max, rgb[a:b],
                 opacity[a:b], depth[a:b], weights[a:b], after[lo:hi], sums[lo:hi])


@compiled_parallel
def _backward_parts(s: Any, slot: Any, far: Any, sig: Any, col: Any, bg: Any, tau_max: Any,
                    g_rgb: Any, g_opacity: Any, g_depth: Any, g_sig: Any, g_col: Any,
                    after: Any, sums: Any, p: int) -> None:
    """:func:`_backward` on ``p`` equal ranges of the rays at once (a row belongs to one
    ray, so the ranges write disjoint rows)."""
    n = s.shape[0]
    for part in prange(p):
        a, b = n * part // p, n * (part + 1) // p
        _backward(s[a:b], slot[a:b], far[a:b], sig, col, bg[a:b], tau_max, g_rgb[a:b],
                  g_opacity[a:b], g_depth[a:b], g_sig, g_col, after[a:b], sums[a:b])


class CompositeRows(torch.autograd.Function):
    """``(σ [M], c [M, 3], s [n, K], slot [n, K], far [n], bg [n, 3])`` →
    ``(rgb [n, 3], opacity [n], depth [n], weights [n, K])`` (module docstring), all
    float32; gradients reach ``σ`` and ``c`` (the weights carry none)."""

    @staticmethod
    def forward(ctx: Any, sig: Tensor, col: Tensor, s: Tensor, slot: Tensor,  # type: ignore[override]
                far: Tensor, bg: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        sig, col = sig.detach().contiguous(), col.detach().contiguous()
        n, k = s.shape
        rgb, opacity, depth = torch.empty(n, 3), torch.empty(n), torch.empty(n)
        weights = torch.empty(n, k)
        args = [x.numpy() for x in (s, slot, far, sig, col, bg)]
        p = parts(n, RAYS_PER_RANGE)
        keep = any(ctx.needs_input_grad[:2])   # the backward pass reads T and Σ w c
        after, sums = torch.empty(n if keep else p, k, dtype=torch.float64), \
            torch.empty(n if keep else p, 3, dtype=torch.float64)
        _forward_parts(*args, _tau_max(), rgb.numpy(), opacity.numpy(), depth.numpy(),
                       weights.numpy(), after.numpy(), sums.numpy(), p, keep)
        ctx.save_for_backward(sig, col, s, slot, far, bg, after, sums)
        ctx.mark_non_differentiable(weights)
        return rgb, opacity, depth, weights

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, g_rgb: Tensor, g_opacity: Tensor, g_depth: Tensor,  # type: ignore[override]
                 _: Tensor) -> tuple[Tensor | None, ...]:
        sig, col, s, slot, far, bg, after, sums = ctx.saved_tensors
        if not any(ctx.needs_input_grad[:2]):    # nothing kept, and no gradient to give
            return None, None, None, None, None, None
        g_sig, g_col = torch.zeros_like(sig), torch.zeros_like(col)
        grads = [g.contiguous().float().numpy() for g in (g_rgb, g_opacity, g_depth)]
        _backward_parts(*(x.numpy() for x in (s, slot, far, sig, col, bg)), _tau_max(),
                        *grads, g_sig.numpy(), g_col.numpy(), after.numpy(), sums.numpy(),
                        parts(s.shape[0], RAYS_PER_RANGE))
        return g_sig, g_col, None, None, None, None


def _tau_max() -> np.float32:
    """:data:`~eventrecon.render.samplers.TAU_MAX` in the compositing's dtype."""
    return np.float32(TAU_MAX)


def composite_rows(sig: Tensor, col: Tensor, s: Tensor, slot: Tensor, far: Tensor,
                   bg: Tensor) -> dict[str, Tensor]:
    """:class:`CompositeRows` as the renderer's level dict: ``rgb``, ``opacity``,
    ``depth``, ``weights`` and ``s`` (contiguous float32 CPU tensors; ``slot`` int64)."""
    rgb, opacity, depth, weights = CompositeRows.apply(sig.float(), col.float(), s, slot,
                                                       far, bg)
    return {"rgb": rgb, "opacity": opacity, "depth": depth, "weights": weights, "s": s}


@compiled
def _merge(s_c: Any, slot_c: Any, s_f: Any, slot_f: Any, keys: Any, ends: Any,
           end_rows: Any, s_u: Any, slot_u: Any) -> None:
    """The union ``s_u, slot_u [n, K_c + K_f]`` of two sorted lists per ray (ties: the
    first list's sample first; a NaN distance sorts last, as in ``torch.sort``). Scratch
    ``keys, ends, end_rows [K_c + K_f + 2]``: each list and an infinite last sample, so
    that every read is in bounds; each step's choice is one comparison and ``&``, ``|``
    on the counts, which compile to selects rather than branches (a branchy merge took
    7 ns per sample here, this one 3.8)."""
    kc, kf = s_c.shape[1], s_f.shape[1]
    last = kc + kf + 1
    for r in range(s_c.shape[0]):
        for q in range(kc):
            ends[q], end_rows[q] = s_c[r, q], slot_c[r, q]
        for q in range(kf):
            ends[kc + 1 + q], end_rows[kc + 1 + q] = s_f[r, q], slot_f[r, q]
        ends[kc], ends[last] = np.inf, np.inf
        for q in range(last + 1):
            keys[q] = ends[q] if ends[q] == ends[q] else np.inf
        i, j = 0, kc + 1
        for q in range(kc + kf):
            first = (i < kc) & ((j == last) | (keys[i] <= keys[j]))
            s_u[r, q] = ends[i] if first else ends[j]
            slot_u[r, q] = end_rows[i] if first else end_rows[j]
            i += first
            j += 1 - first


@compiled_parallel
def _merge_parts(s_c: Any, slot_c: Any, s_f: Any, slot_f: Any, keys: Any, ends: Any,
                 end_rows: Any, s_u: Any, slot_u: Any) -> None:
    """:func:`_merge` on ``P`` equal ranges of the rays at once (``keys, ends, end_rows
    [P, K_c + K_f + 2]``: each range's scratch)."""
    n, p = s_c.shape[0], keys.shape[0]
    for part in prange(p):
        a, b = n * part // p, n * (part + 1) // p
        _merge(s_c[a:b], slot_c[a:b], s_f[a:b], slot_f[a:b], keys[part], ends[part],
               end_rows[part], s_u[a:b], slot_u[a:b])


def merge(s_c: Tensor, slot_c: Tensor, s_f: Tensor, slot_f: Tensor) -> tuple[Tensor, Tensor]:
    """The sorted union of the samples ``s_c [n, K_c]``, ``s_f [n, K_f]`` (each sorted)
    with their slots: ``(s [n, K_c + K_f], slot [n, K_c + K_f])``. ``torch.sort`` is not
    stable, so at two equal distances it may order them the other way."""
    n, k = s_c.shape[0], s_c.shape[1] + s_f.shape[1]
    s_u, slot_u = torch.empty(n, k), torch.empty(n, k, dtype=torch.int64)
    p = parts(n, RAYS_PER_RANGE)
    _merge_parts(s_c.numpy(), slot_c.numpy(), s_f.numpy(), slot_f.numpy(),
                 np.empty((p, k + 2), np.float32), np.empty((p, k + 2), np.float32),
                 np.empty((p, k + 2), np.int64), s_u.numpy(), slot_u.numpy())
    return s_u, slot_u
