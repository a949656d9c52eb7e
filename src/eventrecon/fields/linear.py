"""Linear layers applied through their parameters: ``b + (s·h) Wᵀ``, optionally with the
ReLU that follows fused into the product.

``h [N, in]``, ``W [out, in]``, ``b [out]`` and a scale ``s`` on the activations (the
NeRF MLP's ``2·ReLU``, :mod:`eventrecon.fields.nerf`) that is applied to the weight
instead, ``(s·h) Wᵀ = h (s·W)ᵀ``: exact for a power of two.

**The fused ReLU.** :func:`linear_relu` computes ``max(0, b + h (s·W)ᵀ)``. With grad mode
off (evaluation images, curve points, the occupancy grid's queries), where ``h`` is bf16
on a CPU that computes in bf16 natively, it calls oneDNN's linear with a ReLU post-op
(``torch.ops.mkldnn._linear_pointwise``, a private operator of the pinned torch, the one
inductor's CPU fusion emits) instead of ``addmm`` followed by ``relu``: the activations
are written once instead of being read and written again, and oneDNN's linear primitive
is itself faster than ``addmm`` on these shapes (16 384 rows, 2 cores, Zen 4: 102→64
0.70 → 0.56 ms, 64→64 0.50 → 0.37 ms, 64→32 0.27 → 0.20 ms; a 346×260 image of the 4×64
NeRF 1.13× faster as the median of interleaved pairs, 1.09× on the medians). Its values
were measured identical to ``addmm`` then ``relu``, bit for bit, with torch 2.13 on that
CPU (``tests/test_linear.py`` checks it wherever the fused path runs): not a property of
the method, since the two run different oneDNN primitives. With grad mode on (training
steps) it is ``addmm`` and ``relu``: a fused forward with autograd's backward written out
gave the same gradients but was 4–6 % slower per field step (4 096–16 384 rows), the
``relu`` pass it saves being cheaper than the autograd function around it. Anywhere else
(fp32, a GPU, a CPU without native bf16, a build without oneDNN) it is
``relu(addmm(...))``.

:func:`linear` (the layers without a ReLU) runs oneDNN's linear without a post-op under
the same conditions, for layers of at least :data:`POINTWISE_MIN_OUT` outputs: equal to
``addmm``'s values bit for bit as measured (``tests/test_linear.py``), 1.04× faster for a
fresh field's image and 1.005× for a trained one (docs/results/history.md, "Session 55").
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from eventrecon.precision import cpu_has_native_bf16

__all__ = ["linear", "linear_relu"]


def _fused_op() -> Callable[..., Tensor] | None:
    """oneDNN's linear with a post-op, where oneDNN runs bf16 and the CPU has it natively
    (the only place its speed was measured); ``None`` elsewhere."""
    op = getattr(torch.ops.mkldnn, "_linear_pointwise", None)
    supported = getattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", None)
    if (op is None or supported is None or not torch.backends.mkldnn.is_available()
            or not supported() or not cpu_has_native_bf16()):
        return None
    return op


#: ``torch.ops.mkldnn._linear_pointwise`` where it pays (:func:`_fused_op`), else ``None``.
_POINTWISE: Callable[..., Tensor] | None = _fused_op()


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
    """Whether oneDNN's linear runs this product (module docstring): grad mode off, ``h``
    bf16 on a CPU with native bf16, and the weight and bias cast to bf16 as autocast's
    ``addmm`` casts them (or bf16 already)."""
    castable = (torch.float32, h.dtype)                  # what autocast casts, or bf16
    cast = ((torch.is_autocast_enabled("cpu") and torch.get_autocast_dtype("cpu") == h.dtype
             and weight.dtype in castable and bias.dtype in castable)
            or weight.dtype == bias.dtype == h.dtype)
    return (_POINTWISE is not None and not torch.is_grad_enabled() and h.device.type == "cpu"
            and h.dtype == torch.bfloat16 and cast)


def linear(weight: Tensor, bias: Tensor, h: Tensor, scale: float = 1.0) -> Tensor:
    """``b + h (s·W)ᵀ`` → ``[N, out]``: oneDNN's linear without a post-op where
    :func:`linear_relu` fuses (and the layer has at least :data:`POINTWISE_MIN_OUT`
    outputs), one ``addmm`` otherwise; the same values."""
    weight = _scaled(weight, h, scale)
    if weight.shape[0] < POINTWISE_MIN_OUT or not _fusable(weight, bias, h):
        return torch.addmm(bias, h, weight.t())
    return _POINTWISE(h, weight.to(h.dtype), bias.to(h.dtype), "none", [], "")


def linear_relu(weight: Tensor, bias: Tensor, h: Tensor, scale: float = 1.0) -> Tensor:
    """``max(0, b + h (s·W)ᵀ)`` → ``[N, out]``, fused with grad mode off where ``h`` is
    bf16 on a CPU (module docstring). Under autocast the weight and bias are cast to bf16
    as autocast's ``addmm`` casts them; without it they must be bf16 already, as
    ``addmm`` requires."""
    weight = _scaled(weight, h, scale)
    if not _fusable(weight, bias, h):
        return torch.relu(torch.addmm(bias, h, weight.t()))
    return _POINTWISE(h, weight.to(h.dtype), bias.to(h.dtype), "relu", [], "")
