"""The linear layers of the NeRF MLP: oneDNN's fused ReLU gives addmm-then-relu's values,
to the bit in bf16 and within float32's rounding bound in fp32."""

from __future__ import annotations

from typing import Any

import pytest
import torch
from torch import Tensor

import eventrecon.fields.linear as lin
from eventrecon.fields.linear import linear, linear_relu
from eventrecon.fields.nerf import NeRFField

bf16_fused_only = pytest.mark.skipif(not lin._BF16_FUSES,
                                     reason="no oneDNN bf16 linear or no native bf16 here")
fp32_fused_only = pytest.mark.skipif(lin._POINTWISE is None,
                                     reason="no oneDNN linear in this build of torch")

#: Unit roundoff of float32.
U32 = 2.0 ** -24


def rounding_bound(w: Tensor, b: Tensor, h: Tensor) -> Tensor:
    """``n·u·(|h| |W|ᵀ + |b|)`` ``[N, out]``: the classic bound on the error of a float32
    ``b + h Wᵀ`` summed in any order over its ``n`` inputs (plus the bias), in float64."""
    n = h.shape[1] + 1
    return n * U32 * (h.double().abs() @ w.double().abs().t() + b.double().abs())


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


@bf16_fused_only
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


@fp32_fused_only
@pytest.mark.parametrize("scale", [1.0, 2.0])
@pytest.mark.parametrize("shape", [(1000, 102, 64), (777, 64, 32), (3, 5, 7)])
def test_fp32_fused_relu_is_within_float32_rounding_of_the_exact_product(shape, scale,
                                                                          fused_calls) -> None:
    """In fp32 with grad mode off, oneDNN's linear (with and without its ReLU post-op) and
    ``addmm`` both lie within ``n·u·(|h| |s·W|ᵀ + |b|)`` of the exact product computed in
    float64; the bound is tight enough to mean something (below 1e-4 of the values'
    scale here), and the ReLU cuts the same entries wherever the product is not within
    rounding of zero."""
    n, i, o = shape
    g = torch.Generator().manual_seed(n)
    h, w, b = (torch.randn(n, i, generator=g), torch.randn(o, i, generator=g),
               torch.randn(o, generator=g))
    exact = torch.addmm(b.double(), h.double(), (w.double() * scale).t())
    bound = rounding_bound(w * scale, b, h)
    with torch.no_grad():
        got, plain = linear_relu(w, b, h, scale), linear(w, b, h, scale)
        reference = torch.addmm(b, h, (w * scale).t())
    assert fused_calls == [(n, i)] * 2
    assert got.dtype == plain.dtype == torch.float32
    assert ((plain.double() - exact).abs() <= bound).all()
    assert ((reference.double() - exact).abs() <= bound).all()
    assert ((got.double() - exact.clamp_min(0)).abs() <= bound).all()
    assert float((bound / exact.abs().mean()).max()) < 1e-4
    decided = exact.abs() > bound
    assert torch.equal((got > 0)[decided], (exact > 0)[decided])
    assert (got == 0).any() and (got > 0).any()               # the ReLU cut something


def test_training_and_mixed_dtypes_keep_addmm(fused_calls) -> None:
    """Nothing runs oneDNN's linear with grad mode on (training), for fp32 activations
    under bf16 autocast (``addmm`` computes those in bf16), for bf16 activations with
    fp32 parameters outside autocast, or fp64 parameters under bf16 autocast (both stay
    ``addmm``'s dtype error), with a ReLU or without."""
    h, w, b = torch.randn(50, 8), torch.randn(4, 8), torch.randn(4)
    with torch.no_grad():
        with torch.autocast("cpu", dtype=torch.bfloat16):
            assert torch.equal(linear_relu(w, b, h), torch.relu(torch.addmm(b, h, w.t())))
            assert torch.equal(linear(w, b, h), torch.addmm(b, h, w.t()))
        for fn in (linear_relu, linear):
            with pytest.raises(RuntimeError):
                fn(w, b, h.bfloat16())
            with pytest.raises(RuntimeError), torch.autocast("cpu", dtype=torch.bfloat16):
                fn(w.double(), b.double(), h.bfloat16())    # autocast casts fp32 only
    w.requires_grad_(True)
    out = linear_relu(w, b, h) + linear(w, b, h)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = out + linear_relu(w, b, h.bfloat16()) + linear(w, b, h.bfloat16())
    out.float().sum().backward()
    assert fused_calls == [] and w.grad is not None


@fp32_fused_only
@pytest.mark.parametrize("dtype", [
    torch.float32,
    pytest.param(torch.bfloat16, marks=bf16_fused_only)])
def test_a_single_output_column_keeps_addmm(dtype, fused_calls) -> None:
    """The density head's shape (one output) stays ``addmm`` (faster there); two outputs
    take oneDNN's linear, in bf16 to ``addmm``'s bit, in fp32 within float32's rounding
    bound of the exact product."""
    h = torch.randn(300, 64).to(dtype)
    with torch.no_grad():
        for out in (1, 2):
            w, b = torch.randn(out, 64).to(dtype), torch.randn(out).to(dtype)
            got, want = linear(w, b, h), torch.addmm(b, h, w.t())
            if out == 1 or dtype == torch.bfloat16:
                assert torch.equal(got, want)
            else:
                exact = torch.addmm(b.double(), h.double(), w.double().t())
                assert ((got.double() - exact).abs() <= rounding_bound(w, b, h)).all()
    assert fused_calls == [(300, 64)]


@fp32_fused_only
@pytest.mark.parametrize("dtype", [
    torch.float32,
    pytest.param(torch.bfloat16, marks=bf16_fused_only)])
@pytest.mark.parametrize("sizes", [dict(depth=4, width=64, skip=-1, remap_width=64,
                                        colour_width=32),
                                   dict(depth=4, width=32, skip=1, remap_width=32,
                                        colour_width=16)])
def test_nerf_field_renders_the_same_with_and_without_the_fused_relu(sizes, dtype,
                                                                     fused_calls,
                                                                     monkeypatch) -> None:
    """The field with grad mode off (an evaluation image's query), in fp32 and under bf16
    autocast, with and without the skip: its hidden layers and colour layer fuse their
    ReLU and the colour remap and output layers run oneDNN's linear (the one-column
    density head keeps ``addmm``), and σ and rgb are those of ``addmm`` everywhere: to the
    bit in bf16, within 1e-6 (a few float32 units at the values' scale) in fp32."""
    torch.manual_seed(0)
    f = NeRFField(**sizes, anneal_steps=0)
    xyz, t = torch.rand(4096, 3) * 2 - 1, torch.rand(4096, 1)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16,
                                         enabled=dtype == torch.bfloat16):
        fused = f(xyz, t)
        assert len(fused_calls) == 7              # 4 hidden, remap, colour hidden, out
        monkeypatch.setattr(lin, "_POINTWISE", None)
        plain = f(xyz, t)
    for a, b in zip(fused, plain):
        assert a.dtype == b.dtype
        if dtype == torch.bfloat16:
            assert torch.equal(a, b)
        else:
            assert float((a - b).abs().max()) <= 1e-6
