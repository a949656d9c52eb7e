"""The sine and cosine of float32 angles together, in one compiled pass.

The Fourier features of the NeRF (:mod:`eventrecon.fields.encoding`) are ``sin A`` and
``cos A`` of the same angles. On a CPU, :func:`sin_cos` computes both for float32 angles
in one vectorised loop (two ranges on two threads, :func:`eventrecon.compiled.parts`):

- a Cody–Waite reduction by π/2, ``q = rint(A·2/π)``, ``r = ((A − q·C₁) − q·C₂) − q·C₃``
  with π/2 = C₁ + C₂ + C₃ split into float32 parts, the first two of 11 significant bits,
  so that ``q·C₁`` and ``q·C₂`` are exact for ``|q| < 2¹³``, i.e. ``|A| <`` :data:`LIMIT`;
- Taylor polynomials of ``sin r`` to ``r⁹`` and ``cos r`` to ``r¹⁰`` on ``|r| ≤ π/4``
  (truncation below 2·10⁻⁹);
- the quadrant ``q mod 4`` choosing and signing the pair.

Measured against float64: within 0.71 float32 epsilons (2⁻²³) absolute, where
``torch.sin`` is within 0.30; the two differ by at most one unit in the last place. For
65 536 × 49 angles on two cores (AVX2, Zen 3) 2.40 ms against 5.30 ms for ``torch.sin``
and ``torch.cos`` (docs/results/history.md, "Session 65"). Angles of ``|A| ≥``
:data:`LIMIT` or not finite make the whole call take PyTorch's functions, as do other
dtypes, other devices and a missing numba (autograd takes the compiled values too,
its backward ``∂A = ∂s·cos A − ∂c·sin A`` from them): every caller of :func:`sin_cos`
with the same angles gets the same values, which is what keeps the encoding's layouts
equal to one another to the bit.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from eventrecon.compiled import AVAILABLE, compiled, compiled_parallel, parts, prange

__all__ = ["LIMIT", "sin_cos"]

_F = np.float32
#: π/2 in three float32 parts: 11, 11 and 24 significant bits.
_C1, _C2, _C3 = _F(1.5703125), _F(4.837512969970703e-4), _F(7.549790126404332e-08)
_TWO_OVER_PI = _F(2.0 / np.pi)
_S3, _S5, _S7, _S9 = _F(-1 / 6), _F(1 / 120), _F(-1 / 5040), _F(1 / 362880)
_Q2, _Q4, _Q6, _Q8, _Q10 = (_F(-1 / 2), _F(1 / 24), _F(-1 / 720), _F(1 / 40320),
                            _F(-1 / 3628800))
#: Largest |angle| the reduction keeps exact (``|q| ≤ 2¹³ − 1``), a little below it.
LIMIT = 12800.0


@compiled
def _rows(a: Any, s_out: Any, c_out: Any, lo: int, hi: int, limit: Any) -> int:
    """``sin``, ``cos`` of ``a[lo:hi]`` (``[n, F]`` float32) into ``s_out``, ``c_out``;
    returns how many angles were not below ``limit`` in magnitude (or not finite)."""
    one, two = _F(1.0), _F(2.0)
    far = 0
    for i in range(lo, hi):
        for j in range(a.shape[1]):
            x = a[i, j]
            far += not abs(x) < limit
            q = _F(np.rint(x * _TWO_OVER_PI))
            r = ((x - q * _C1) - q * _C2) - q * _C3
            r2 = r * r
            s = r + r * r2 * (_S3 + r2 * (_S5 + r2 * (_S7 + r2 * _S9)))
            c = one + r2 * (_Q2 + r2 * (_Q4 + r2 * (_Q6 + r2 * (_Q8 + r2 * _Q10))))
            k = np.int32(q) & 3
            odd = (k & 1) == 1
            s_out[i, j] = (one - two * _F((k >> 1) & 1)) * (c if odd else s)
            c_out[i, j] = (one - two * _F(((k + 1) >> 1) & 1)) * (s if odd else c)
    return far


@compiled_parallel
def _rows_parts(a: Any, s_out: Any, c_out: Any, p: int, limit: Any) -> int:
    """:func:`_rows` on ``p`` equal ranges of the rows at once (the same values)."""
    n, far = a.shape[0], 0
    for k in prange(p):
        far += _rows(a, s_out, c_out, n * k // p, n * (k + 1) // p, limit)
    return far


def _compiled_applies(angles: Tensor, *outs: Tensor | None) -> bool:
    """Float32 ``[n, F]`` angles on a CPU, numba at hand, and float32 CPU outputs of the
    same shape where given."""
    return (AVAILABLE and angles.device.type == "cpu" and angles.dtype == torch.float32
            and angles.dim() == 2
            and all(o is None or (o.dtype == torch.float32 and o.device.type == "cpu"
                                  and o.shape == angles.shape) for o in outs))


def _compute(angles: Tensor, sin_out: Tensor | None, cos_out: Tensor | None
             ) -> tuple[Tensor, Tensor]:
    """The compiled pass into ``sin_out``, ``cos_out`` (new tensors where ``None``), or
    PyTorch's functions for the whole call where an angle reaches :data:`LIMIT`."""
    a = angles.detach().contiguous()
    s = torch.empty_like(a) if sin_out is None else sin_out
    c = torch.empty_like(a) if cos_out is None else cos_out
    n = a.shape[0]
    k = parts(n)
    args = (a.numpy(), s.numpy(), c.numpy())
    far = _rows(*args, 0, n, _F(LIMIT)) if k == 1 else _rows_parts(*args, k, _F(LIMIT))
    if far:
        torch.sin(a, out=s)
        torch.cos(a, out=c)
    return s, c


class _SinCos(torch.autograd.Function):
    """``angles -> (sin, cos)`` through :func:`_compute`, differentiable:
    ``∂L/∂A = ∂L/∂s · cos A − ∂L/∂c · sin A`` from the same values."""

    @staticmethod
    def forward(ctx: Any, angles: Tensor) -> tuple[Tensor, Tensor]:  # type: ignore[override]
        s, c = _compute(angles, None, None)
        ctx.save_for_backward(s, c)
        return s, c

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: Any, grad_s: Tensor | None, grad_c: Tensor | None) -> Tensor:  # type: ignore[override]
        s, c = ctx.saved_tensors
        grad = torch.zeros_like(s)
        if grad_s is not None:
            grad = grad + grad_s * c
        if grad_c is not None:
            grad = grad - grad_c * s
        return grad


def sin_cos(angles: Tensor, sin_out: Tensor | None = None,
            cos_out: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``(sin A, cos A)`` of ``angles [n, F]``, written into ``sin_out`` and ``cos_out``
    where given (any strides; another dtype takes a cast of the float32 values; not with
    autograd through the angles).

    The compiled pass of the module docstring for float32 angles on a CPU, with or
    without autograd; ``torch.sin`` and ``torch.cos`` otherwise, and for the whole call
    where an angle is not finite or reaches :data:`LIMIT`."""
    outs = (sin_out, cos_out)
    if not _compiled_applies(angles):
        pair = (torch.sin(angles), torch.cos(angles))
    elif angles.requires_grad and torch.is_grad_enabled():
        if sin_out is not None or cos_out is not None:
            raise ValueError("sin_cos: outputs given with autograd through the angles")
        return _SinCos.apply(angles)
    elif _compiled_applies(angles, sin_out, cos_out):
        return _compute(angles, sin_out, cos_out)
    else:
        pair = _compute(angles, None, None)
    return tuple(p if o is None else o.copy_(p) for p, o in zip(pair, outs))  # type: ignore[return-value]
