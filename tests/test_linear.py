"""The linear layers of the NeRF MLP: the fused bf16 ReLU gives addmm-then-relu's values."""

from __future__ import annotations

from typing import Any

import pytest
import torch
from torch import Tensor

import eventrecon.fields.linear as lin
from eventrecon.fields.linear import linear, linear_relu
from eventrecon.fields.nerf import NeRFField

fused_only = pytest.mark.skipif(lin._POINTWISE is None,
                                reason="no oneDNN bf16 linear or no native bf16 here")


@pytest.fixture
def fused_calls(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, ...]]:
    """The input shapes of every fused call (a stand-in that must not run where the
    fused operator is missing)."""
    calls: list[tuple[int, ...]] = []
    op = lin._POINTWISE

    def counted(h: Tensor, *args: Any) -> Tensor:
        calls.append(tuple(h.shape))
        assert op is not None, "the fused path ran without the fused operator"
        return op(h, *args)
    monkeypatch.setattr(lin, "_POINTWISE", counted)
    return calls


@fused_only
@pytest.mark.parametrize("scale", [1.0, 2.0])
@pytest.mark.parametrize("shape", [(1000, 102, 64), (777, 64, 32), (3, 5, 7)])
def test_fused_relu_is_addmm_then_relu_to_the_bit(shape, scale, fused_calls) -> None:
    """Under bf16 autocast with grad mode off: oneDNN's linear with a ReLU post-op equals
    autocast's ``addmm`` followed by ``relu`` exactly, with the weight doubled as the
    ``2·ReLU`` fold doubles it; so does the same call on bf16 parameters without
    autocast; and oneDNN's linear without a post-op (``linear``) equals ``addmm``."""
    n, i, o = shape
    g = torch.Generator().manual_seed(n)
    h = torch.randn(n, i, generator=g).bfloat16()
    w, b = torch.randn(o, i, generator=g), torch.randn(o, generator=g)
    product = torch.addmm(b.bfloat16(), h, (w.bfloat16() * scale).t())
    want = torch.relu(product)
    with torch.no_grad():
        with torch.autocast("cpu", dtype=torch.bfloat16):
            got = linear_relu(w, b, h, scale)
            plain = linear(w, b, h, scale)
        got_bf16 = linear_relu(w.bfloat16(), b.bfloat16(), h, scale)
    assert fused_calls == [(n, i)] * 3
    assert got.dtype == got_bf16.dtype == plain.dtype == torch.bfloat16
    assert torch.equal(got, want) and torch.equal(got_bf16, want)
    assert torch.equal(plain, product)
    assert (want == 0).any() and (want > 0).any()             # the ReLU cut something


def test_fp32_autograd_and_mixed_dtypes_keep_addmm(fused_calls) -> None:
    """Nothing runs oneDNN's linear in fp32, with grad mode on (training), for bf16
    activations with fp32 parameters outside autocast, or fp64 parameters under bf16
    autocast (both stay ``addmm``'s dtype error), with a ReLU or without."""
    h, w, b = torch.randn(50, 8), torch.randn(4, 8), torch.randn(4)
    with torch.no_grad():
        assert torch.equal(linear_relu(w, b, h), torch.relu(torch.addmm(b, h, w.t())))
        assert torch.equal(linear(w, b, h), torch.addmm(b, h, w.t()))
        for fn in (linear_relu, linear):
            with pytest.raises(RuntimeError):
                fn(w, b, h.bfloat16())
            with pytest.raises(RuntimeError), torch.autocast("cpu", dtype=torch.bfloat16):
                fn(w.double(), b.double(), h.bfloat16())    # autocast casts fp32 only
    w.requires_grad_(True)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = linear_relu(w, b, h.bfloat16()) + linear(w, b, h.bfloat16())
    out.float().sum().backward()
    assert fused_calls == [] and w.grad is not None


@fused_only
def test_a_single_output_column_keeps_addmm(fused_calls) -> None:
    """The density head's shape (one output) stays ``addmm`` (faster there); two outputs
    take oneDNN's linear. Both give ``addmm``'s values."""
    h = torch.randn(300, 64).bfloat16()
    with torch.no_grad():
        for out in (1, 2):
            w, b = torch.randn(out, 64).bfloat16(), torch.randn(out).bfloat16()
            assert torch.equal(linear(w, b, h), torch.addmm(b, h, w.t()))
    assert fused_calls == [(300, 64)]


@fused_only
@pytest.mark.parametrize("sizes", [dict(depth=4, width=64, skip=-1, remap_width=64,
                                        colour_width=32),
                                   dict(depth=4, width=32, skip=1, remap_width=32,
                                        colour_width=16)])
def test_nerf_field_renders_the_same_with_and_without_the_fused_relu(sizes, fused_calls,
                                                                     monkeypatch) -> None:
    """The field with grad mode off under bf16 autocast (an evaluation image's query),
    with and without the skip: the same σ and rgb to the bit whether its hidden layers
    and colour layer fuse their ReLU and the colour remap and output layers run oneDNN's
    linear or not (the one-column density head keeps ``addmm``)."""
    torch.manual_seed(0)
    f = NeRFField(**sizes, anneal_steps=0)
    xyz, t = torch.rand(4096, 3) * 2 - 1, torch.rand(4096, 1)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        fused = f(xyz, t)
        assert len(fused_calls) == 7              # 4 hidden, remap, colour hidden, out
        monkeypatch.setattr(lin, "_POINTWISE", None)
        plain = f(xyz, t)
    for a, b in zip(fused, plain):
        assert torch.equal(a, b)
