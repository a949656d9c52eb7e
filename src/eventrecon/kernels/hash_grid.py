"""The 4D hash encoding's corner gather and its gradient in compiled loops on the CPU.

The PyTorch reference is :meth:`baselines.ngp.HashEncoding.forward` (its vectorised
corners and ``embedding_bag``). For level ``l`` (``R_{l,k}`` cells along axis ``k``,
table rows from ``o_l``) a point ``u [D]`` has, per axis, the lower vertex
``i_k = min(⌊u_k R_{l,k}⌋, R_{l,k} − 1)`` (``u`` clamped to ``[0, 1]``), the weights
``w_k(0) = 1 − f_k``, ``w_k(1) = f_k`` with ``f_k = u_k R_{l,k} − i_k``, and the terms
``v_k(b) = (i_k + b)·m_k`` (``m_k`` the dense stride or the hash prime; masked by
``T − 1`` at hashed levels). Corner ``c = Σ_k b_k 2^k`` reads row

.. math::
    r_c = o_l + (v_{D-1} ⊕ (\\dots ⊕ (v_1 ⊕ v_0))),\\qquad
    w_c = w_{D-1}(b_{D-1}) (\\dots (w_1(b_1)\\, w_0(b_0))),

``⊕`` being ``+`` at dense levels and XOR at hashed ones, and the level's features are
``e_l = Σ_{c=0}^{2^D-1} w_c T[r_c]``, summed in ``c`` order. The gradient scatters
``∂L/∂T[r_c] += w_c ∂L/∂e_l`` in the same order, point after point.

Why: the reference builds ``[N, L, 16]`` rows and weights in ~40 tensor operations and
streams them through memory twice. Here a point's 8 per-axis terms sit in a scratch
row, its 16 rows and weights and its two sums in registers, and the loops run level by
level, so one level's table (1 MB at 2^17 rows) stays in cache while every point reads
it. With two or more torch threads the work is split between numba's threads
(:func:`~eventrecon.kernels.jit.parts`): the forward by points, the gradient by levels,
which own disjoint table rows, so neither needs a reduction and both give the same bits
at any thread count.

The rows and weights are the reference's, computed with the same float32 expressions;
the sums run in corner order, so the values agree with ``embedding_bag``'s to rounding,
and the gradient, accumulated in float32 point after point, to rounding as well. A point
with a NaN coordinate reads NaN at every level and sends no gradient. The loops are
written for the NGP field's 4 axes and 2 features; :func:`unsupported` says where they
do not apply (other sizes, a GPU, no numba, float64, coordinates that need a gradient).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from eventrecon.common.errors import InputError
from eventrecon.kernels.jit import AVAILABLE, inline, parallel, parts, prange, serial

__all__ = ["Plan", "encode", "unsupported"]


@inline
def _axes(u: Any, n: int, res: Any, mult: Any, hashed: bool, mask: int, v: Any,
          w: Any) -> bool:
    """Point ``n``'s per-axis terms at one level: ``v[2k + b] = v_k(b)`` (int32) and
    ``w[2k + b] = w_k(b)`` (module docstring); False for a NaN coordinate."""
    for k in range(4):
        x = u[n, k]
        if x != x:
            return False
        x = min(max(x, np.float32(0.0)), np.float32(1.0))
        pos = x * np.float32(res[k])
        i = min(int(math.floor(pos)), res[k] - 1)
        f = pos - np.float32(i)
        v0 = i * mult[k]
        v1 = v0 + mult[k]
        if hashed:
            v0 &= mask
            v1 &= mask
        v[2 * k], v[2 * k + 1] = np.int32(v0), np.int32(v1)
        w[2 * k], w[2 * k + 1] = np.float32(1.0) - f, f
    return True


@inline
def _corner(v: Any, w: Any, hashed: bool, offset: int, c: int) -> tuple[int, Any]:
    """Corner ``c``'s row and weight from :func:`_axes`' terms, combined as the reference
    does: ``v_3 ⊕ (v_2 ⊕ (v_1 ⊕ v_0))`` and ``w_3 (w_2 (w_1 w_0))``."""
    b0, b1, b2, b3 = c & 1, 2 + ((c >> 1) & 1), 4 + ((c >> 2) & 1), 6 + ((c >> 3) & 1)
    if hashed:
        row = v[b3] ^ (v[b2] ^ (v[b1] ^ v[b0]))
    else:
        row = v[b3] + (v[b2] + (v[b1] + v[b0]))
    return row + offset, w[b3] * (w[b2] * (w[b1] * w[b0]))


@serial
def _encode(u: Any, res: Any, mult: Any, hashed: Any, offset: Any, mask: int, table: Any,
            l0: int, l1: int, out: Any, v: Any, w: Any) -> None:
    """``out [N, 2L]``'s columns of levels ``l0 .. l1 − 1`` (4 axes, 2 features; the two
    sums kept in registers); ``v, w [8]`` scratch."""
    for lvl in range(l0, l1):
        for n in range(u.shape[0]):
            e0 = e1 = np.float32(np.nan)
            if _axes(u, n, res[lvl], mult[lvl], hashed[lvl], mask, v, w):
                e0 = e1 = np.float32(0.0)
                for c in range(16):
                    row, wc = _corner(v, w, hashed[lvl], offset[lvl], c)
                    e0 += wc * table[row, 0]
                    e1 += wc * table[row, 1]
            out[n, 2 * lvl], out[n, 2 * lvl + 1] = e0, e1


@serial
def _scatter(u: Any, res: Any, mult: Any, hashed: Any, offset: Any, mask: int, grad: Any,
             l0: int, l1: int, g_table: Any, v: Any, w: Any) -> None:
    """``g_table[r_c] += w_c grad[n, level's 2 columns]`` for levels ``l0 .. l1 − 1``."""
    for lvl in range(l0, l1):
        for n in range(u.shape[0]):
            if _axes(u, n, res[lvl], mult[lvl], hashed[lvl], mask, v, w):
                g0, g1 = grad[n, 2 * lvl], grad[n, 2 * lvl + 1]
                for c in range(16):
                    row, wc = _corner(v, w, hashed[lvl], offset[lvl], c)
                    g_table[row, 0] += wc * g0
                    g_table[row, 1] += wc * g1


@parallel
def _encode_parts(u: Any, res: Any, mult: Any, hashed: Any, offset: Any, mask: int,
                  table: Any, out: Any, v: Any, w: Any) -> None:
    """:func:`_encode` on ``P`` equal ranges of the points at once (``v, w [P, ≥ 8]``)."""
    n, p = u.shape[0], v.shape[0]
    for k in prange(p):
        a, b = n * k // p, n * (k + 1) // p
        _encode(u[a:b], res, mult, hashed, offset, mask, table, 0, res.shape[0], out[a:b],
                v[k], w[k])


@parallel
def _scatter_parts(u: Any, res: Any, mult: Any, hashed: Any, offset: Any, mask: int,
                   grad: Any, g_table: Any, v: Any, w: Any) -> None:
    """:func:`_scatter` with the levels split into ``P`` ranges (disjoint table rows;
    ``v, w [P, ≥ 8]``)."""
    n_levels, p = res.shape[0], v.shape[0]
    for k in prange(p):
        _scatter(u, res, mult, hashed, offset, mask, grad, n_levels * k // p,
                 n_levels * (k + 1) // p, g_table, v[k], w[k])


class Plan:
    """An encoding's constants for the compiled loops; ``rows`` is the table's rows in
    all, which :func:`unsupported` checks the table against (the loops do not check
    their indices).

    Args:
        res: ``[L, D]`` int64, ``R_{l,k}``.
        mult: ``[L, D]`` int64, ``m_k``: the dense strides or the hash primes.
        hashed: ``[L]`` bool, whether a level is hashed (else indexed densely).
        offsets: each level's first table row (``L + 1`` entries, the last the total).
        table_size: ``T``, a power of two (hashed levels keep ``T − 1``'s bits).
    """

    def __init__(self, res: np.ndarray, mult: np.ndarray, hashed: np.ndarray,
                 offsets: Sequence[int], table_size: int) -> None:
        self.res, self.mult = np.ascontiguousarray(res), np.ascontiguousarray(mult)
        self.hashed = np.ascontiguousarray(hashed, dtype=np.bool_)
        self.offset = np.asarray(offsets[:-1], dtype=np.int32)
        self.mask = int(table_size - 1)
        self.rows = int(offsets[-1])

    def scratch(self, p: int) -> tuple[np.ndarray, np.ndarray]:
        """Each range's per-axis terms, int32 and float32, in rows of 128 bytes (``[P,
        32]``, 8 used): two threads writing one cache line would stall each other."""
        return np.empty((p, 32), np.int32), np.empty((p, 32), np.float32)

    def args(self) -> tuple:
        """The constants in the compiled loops' argument order."""
        return self.res, self.mult, self.hashed, self.offset, self.mask


class _Encode(torch.autograd.Function):
    """``(table [rows, 2], u [N, 4], plan) -> [N, 2L]``; the gradient reaches the table."""

    @staticmethod
    def forward(ctx: Any, table: Tensor, u: Tensor, plan: Plan) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(u)
        ctx.plan = plan
        return _run_encode(table, u, plan)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None, None]:  # type: ignore[override]
        (u,) = ctx.saved_tensors
        plan = ctx.plan
        g = grad.contiguous().float()
        n_levels = plan.res.shape[0]
        g_table = torch.zeros(plan.rows, 2, dtype=torch.float32)
        p = min(parts(u.shape[0]), n_levels)          # ranges of levels: no reduction
        v, w = plan.scratch(p)
        if p == 1:
            _scatter(u.numpy(), *plan.args(), g.numpy(), 0, n_levels, g_table.numpy(), v[0],
                     w[0])
        else:
            _scatter_parts(u.numpy(), *plan.args(), g.numpy(), g_table.numpy(), v, w)
        return g_table, None, None


def _run_encode(table: Tensor, u: Tensor, plan: Plan) -> Tensor:
    """The forward pass: ``[N, L·F]`` float32."""
    n_levels = plan.res.shape[0]
    out = torch.empty(u.shape[0], n_levels * table.shape[1], dtype=torch.float32)
    p = parts(u.shape[0])                            # ranges of points
    v, w = plan.scratch(p)
    t = table.detach().numpy()
    if p == 1:
        _encode(u.numpy(), *plan.args(), t, 0, n_levels, out.numpy(), v[0], w[0])
    else:
        _encode_parts(u.numpy(), *plan.args(), t, out.numpy(), v, w)
    return out


def unsupported(table: Tensor, u: Tensor, plan: Plan) -> str | None:
    """What :func:`encode` needs and this call lacks, or ``None`` where it applies: it
    needs numba, a float32 table of the plan's rows and 2 features, ``[N, 4]`` float32
    coordinates on the CPU that need no gradient, and a plan of 4 axes.

    >>> plan = Plan(np.ones((1, 4), np.int64), np.ones((1, 4), np.int64), np.zeros(1),
    ...             [0, 16], 16)
    >>> unsupported(torch.zeros(16, 2), torch.zeros(3, 4).double(), plan)
    'coordinates [N, 4] in float32'
    """
    if not AVAILABLE:
        return "numba installed"
    if table.device.type != "cpu" or u.device.type != "cpu":
        return "tensors on the CPU"
    if plan.res.shape[1] != 4:
        return "4 input axes"
    if table.dtype != torch.float32 or table.shape != (plan.rows, 2):
        return f"a float32 table of {plan.rows} rows and 2 features"
    if u.dtype != torch.float32 or u.dim() != 2 or u.shape[1] != 4:
        return "coordinates [N, 4] in float32"
    if u.requires_grad and torch.is_grad_enabled():
        return "no gradient with respect to the coordinates"
    return None


def encode(table: Tensor, u: Tensor, plan: Plan) -> Tensor:
    """``[N, L·F]``: the encoding of ``plan`` with ``table [rows, F]`` at ``u [N, D]``
    (module docstring), differentiable with respect to the table.

    Raises:
        InputError: :func:`unsupported` names a reason.
    """
    reason = unsupported(table, u, plan)
    if reason is not None:
        raise InputError("eventrecon.kernels.hash_grid", "encode", reason)
    u = u.detach().contiguous()
    if torch.is_grad_enabled() and table.requires_grad:
        return _Encode.apply(table, u, plan)
    return _run_encode(table, u, plan)
