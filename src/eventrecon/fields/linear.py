"""Linear layers applied through their parameters: ``b + (s·h) Wᵀ``, optionally with the
ReLU that follows fused into the product.

``h [N, in]``, ``W [out, in]``, ``b [out]`` and a scale ``s`` on the activations (the
NeRF MLP's ``2·ReLU``, :mod:`eventrecon.fields.nerf`) that is applied to the weight
instead, ``(s·h) Wᵀ = h (s·W)ᵀ``: exact for a power of two.

**The fused ReLU.** :func:`linear_relu` computes ``max(0, b + h (s·W)ᵀ)``. With grad mode
off (evaluation images, curve points, the occupancy grid's queries) on a CPU it calls
oneDNN's linear with a ReLU post-op (``torch.ops.mkldnn._linear_pointwise``, a private
operator of the pinned torch, the one inductor's CPU fusion emits) instead of ``addmm``
followed by ``relu``: the activations are written once instead of being read and written
again, and oneDNN's linear primitive is itself faster than ``addmm`` on these shapes. Two
cases run it:

- **bf16** activations on a CPU that computes in bf16 natively (16 384 rows, 2 cores,
  Zen 4: 102→64 0.70 → 0.56 ms, 64→64 0.50 → 0.37 ms, 64→32 0.27 → 0.20 ms; a 346×260
  image of the 4×64 NeRF 1.13× faster as the median of interleaved pairs). Its values
  were measured identical to ``addmm`` then ``relu``, bit for bit, with torch 2.13 on that
  CPU, and ``tests/test_linear.py`` checks it wherever this path runs.
- **fp32** activations, weight and bias outside autocast (a run in ``32-true``: the
  NeRF on a CPU without native bf16, ``eventrecon.precision``), on any CPU. On a 2-core
  AVX2-only EPYC (Zen 3), the only CPU it was timed on, the layers ran 1.23–1.35× faster
  at 16 384 rows and the 346×260 image 1.17–1.23× (docs/results/history.md, sessions
  64–65). oneDNN blocks the sums over the inputs differently from MKL's ``addmm``, so
  the values agree to float32 rounding, not to the bit: within ``n·u·(|h| |s·W|ᵀ + |b|)``
  for ``n`` inputs and unit roundoff ``u = 2⁻²⁴``, the standard bound on a float32 dot
  product's error, which ``tests/test_linear.py`` asserts (a 346×260 image's colours
  moved by ≤ 6·10⁻⁸).

With grad mode on (training steps) it is ``addmm`` and ``relu``: a fused forward with
autograd's backward written out gave the same gradients but was 4–6 % slower per field
step in bf16 (4 096–16 384 rows), the ``relu`` pass it saves being cheaper than the
autograd function around it, and 1.01–1.07× in fp32 (18 000–36 000 rows, Zen 3; session
65), not worth a second backward to maintain. Anywhere else (a GPU, bf16 on a CPU
without native bf16, fp16, a build without oneDNN) it is ``relu(addmm(...))``.

:func:`linear` (the layers without a ReLU) runs oneDNN's linear without a post-op under
the same conditions, for layers of at least :data:`POINTWISE_MIN_OUT` outputs: in bf16
equal to ``addmm``'s values bit for bit as measured (``tests/test_linear.py``), 1.04×
faster for a fresh field's image and 1.005× for a trained one (docs/results/history.md,
"Session 55"); in fp32 within the same rounding bound as the ReLU layers.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from eventrecon.precision import cpu_has_native_bf16

__all__ = ["linear", "linear_relu"]


def _fused_op() -> Callable[..., Tensor] | None:
    """oneDNN's linear with a post-op where this build of torch has it; ``None`` where it
    does not (no oneDNN, or a torch without the operator)."""
    op = getattr(torch.ops.mkldnn, "_linear_pointwise", None)
    if op is None or not torch.backends.mkldnn.is_available():
        return None
    return op


def _bf16_fuses() -> bool:
    """Whether oneDNN runs bf16 here and the CPU has it natively (the only place the
    bf16 call's speed was measured)."""
    supported = getattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", None)
    return supported is not None and bool(supported()) and cpu_has_native_bf16()


#: ``torch.ops.mkldnn._linear_pointwise`` where the build has it (:func:`_fused_op`).
_POINTWISE: Callable[..., Tensor] | None = _fused_op()
#: Whether bf16 activations take it (:func:`_bf16_fuses`); fp32 ones do wherever it exists.
_BF16_FUSES: bool = _POINTWISE is not None and _bf16_fuses()


def _scaled(weight: Tensor, h: Tensor, scale: float) -> Tensor:
    """The weight ``s·W`` as the product sees it. Under autocast the weight is
    cast to the compute dtype before it is scaled, so the product uses ``s·cast(W)`` as
    the explicit form would (casting ``s·W`` instead rounds differently where ``W`` is
    subnormal in fp16)."""
    if scale != 1.0:
        device = h.device.type
        if torch.is_autocast_enabled(device):
            weight = weight.to(torch.get_autocast_dtype(device))
        weight = weight * scale
    return weight


#: Layers with fewer outputs than this keep ``addmm`` where oneDNN's linear could run: for
#: a single output column (the NeRF's density head, 16 384 rows) oneDNN took 128 against
#: ``addmm``'s 97 µs, while 64→64 ran in 362 against 394 µs and 32→3 in 78 against 129.
POINTWISE_MIN_OUT = 2


def _fusable(weight: Tensor, bias: Tensor, h: Tensor) -> bool:
    """Whether oneDNN's linear runs this product (module docstring): grad mode off on a
    CPU, and either ``h`` bf16 on a CPU with native bf16, with the weight and bias cast to
    bf16 as autocast's ``addmm`` casts them (or bf16 already), or ``h``, the weight and the
    bias all fp32 outside autocast (under it ``addmm`` would compute in bf16)."""
    if _POINTWISE is None or torch.is_grad_enabled() or h.device.type != "cpu":
        return False
    if h.dtype == torch.float32:
        return (weight.dtype == bias.dtype == torch.float32
                and not torch.is_autocast_enabled("cpu"))
    castable = (torch.float32, h.dtype)                  # what autocast casts, or bf16
    cast = ((torch.is_autocast_enabled("cpu") and torch.get_autocast_dtype("cpu") == h.dtype
             and weight.dtype in castable and bias.dtype in castable)
            or weight.dtype == bias.dtype == h.dtype)
    return _BF16_FUSES and h.dtype == torch.bfloat16 and cast


def linear(weight: Tensor, bias: Tensor, h: Tensor, scale: float = 1.0) -> Tensor:
    """``b + h (s·W)ᵀ`` → ``[N, out]``: oneDNN's linear without a post-op where
    :func:`linear_relu` fuses (and the layer has at least :data:`POINTWISE_MIN_OUT`
    outputs), one ``addmm`` otherwise; the same values in bf16, to float32 rounding in
    fp32."""
    weight = _scaled(weight, h, scale)
    if weight.shape[0] < POINTWISE_MIN_OUT or not _fusable(weight, bias, h):
        return torch.addmm(bias, h, weight.t())
    return _POINTWISE(h, weight.to(h.dtype), bias.to(h.dtype), "none", [], "")


def linear_relu(weight: Tensor, bias: Tensor, h: Tensor, scale: float = 1.0) -> Tensor:
    """``max(0, b + h (s·W)ᵀ)`` → ``[N, out]``, fused with grad mode off on a CPU for fp32,
    and for bf16 where the CPU has it natively (module docstring). For bf16 activations
    under autocast the weight and bias are cast to bf16 as autocast's ``addmm`` casts
    them; without it they must be bf16 already, as ``addmm`` requires."""
    weight = _scaled(weight, h, scale)
    if not _fusable(weight, bias, h):
        return torch.relu(torch.addmm(bias, h, weight.t()))
    return _POINTWISE(h, weight.to(h.dtype), bias.to(h.dtype), "relu", [], "")
