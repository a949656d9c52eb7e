"""Linear layers applied through their parameters: ``b + (s·h) Wᵀ``, optionally with the
ReLU that follows fused into the product.

``h [N, in]``, ``W [out, in]``, ``b [out]`` and a scale ``s`` on the activations (the
NeRF MLP's ``2·ReLU``, :mod:`eventrecon.fields.nerf`) that is applied to the weight
instead, ``(s·h) Wᵀ = h (s·W)ᵀ``: exact for a power of two.

**The fused ReLU.** :func:`linear_relu` computes ``max(0, b + h (s·W)ᵀ)``. Without
autograd, where ``h`` is bf16 on a CPU (images rendered under bf16 autocast), it calls
oneDNN's linear with a ReLU post-op (``torch.ops.mkldnn._linear_pointwise``) instead of
``addmm`` followed by ``relu``: the activations are written once instead of being read
and written again, and oneDNN's linear primitive is itself faster than ``addmm`` on these
shapes (16 384 rows, 2 cores, Zen 4: 102→64 0.70 → 0.56 ms, 64→64 0.50 → 0.37 ms, 64→32
0.27 → 0.20 ms; a 346×260 image of the 4×64 NeRF 1.09–1.13× faster). The values are those
of ``addmm`` then ``relu`` to the bit (both accumulate in fp32 and round once to bf16;
``tests/test_linear.py``). Training keeps ``addmm`` and ``relu``: a fused forward with
autograd's backward written out was bit-identical but 2–6 % slower per field step
(4 096–16 384 rows), the ``relu`` pass it saves being cheaper than the autograd function
around it. Anywhere else (fp32, a GPU, a build without oneDNN) it is ``relu(addmm(...))``.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["linear", "linear_relu"]

_POINTWISE = getattr(torch.ops.mkldnn, "_linear_pointwise", None) \
    if torch.backends.mkldnn.is_available() else None


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


def linear(weight: Tensor, bias: Tensor, h: Tensor, scale: float = 1.0) -> Tensor:
    """``b + h (s·W)ᵀ`` in one ``addmm`` → ``[N, out]``."""
    return torch.addmm(bias, h, _scaled(weight, h, scale).t())


def linear_relu(weight: Tensor, bias: Tensor, h: Tensor, scale: float = 1.0) -> Tensor:
    """``max(0, b + h (s·W)ᵀ)`` → ``[N, out]``, fused without autograd where ``h`` is
    bf16 on a CPU (module docstring); the weight and bias are cast to bf16 as autocast's
    ``addmm`` casts them."""
    weight = _scaled(weight, h, scale)
    if (_POINTWISE is None or torch.is_grad_enabled() or h.device.type != "cpu"
            or h.dtype != torch.bfloat16):
        return torch.relu(torch.addmm(bias, h, weight.t()))
    return _POINTWISE(h, weight.to(h.dtype), bias.to(h.dtype), "relu", [], "")
