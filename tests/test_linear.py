"""The linear layers of the NeRF MLP: the fused bf16 ReLU gives addmm-then-relu's values."""

from __future__ import annotations

import pytest
import torch

import eventrecon.fields.linear as lin
from eventrecon.fields.linear import linear, linear_relu
from eventrecon.fields.nerf import NeRFField

pytestmark = pytest.mark.skipif(lin._POINTWISE is None, reason="no oneDNN in this build")


@pytest.fixture
def fused_calls(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, ...]]:
    """The input shapes of every fused call."""
    calls: list[tuple[int, ...]] = []
    op = lin._POINTWISE

    def counted(h, *args):
        calls.append(tuple(h.shape))
        return op(h, *args)
    monkeypatch.setattr(lin, "_POINTWISE", counted)
    return calls


@pytest.mark.parametrize("scale", [1.0, 2.0])
@pytest.mark.parametrize("shape", [(1000, 102, 64), (777, 64, 32), (3, 5, 7)])
def test_fused_relu_is_addmm_then_relu_to_the_bit(shape, scale, fused_calls) -> None:
    """Under bf16 autocast without autograd: oneDNN's linear with a ReLU post-op equals
    autocast's ``addmm`` followed by ``relu`` exactly, with the weight doubled as the
    ``2·ReLU`` fold doubles it; ``linear`` is the same product without the ReLU."""
    n, i, o = shape
    g = torch.Generator().manual_seed(n)
    h = torch.randn(n, i, generator=g).bfloat16()
    w, b = torch.randn(o, i, generator=g), torch.randn(o, generator=g)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        got = linear_relu(w, b, h, scale)
        plain = linear(w, b, h, scale)
        want = torch.relu(torch.addmm(b, h, (w.bfloat16() * scale).t()))
    assert fused_calls == [(n, i)]
    assert got.dtype == want.dtype == torch.bfloat16
    assert torch.equal(got, want) and torch.equal(torch.relu(plain), want)
    assert (want == 0).any() and (want > 0).any()             # the ReLU cut something


def test_fp32_and_autograd_keep_addmm(fused_calls) -> None:
    """In fp32, and in bf16 with autograd on (training), nothing is fused."""
    h, w, b = torch.randn(50, 8), torch.randn(4, 8), torch.randn(4)
    with torch.no_grad():
        assert torch.equal(linear_relu(w, b, h), torch.relu(torch.addmm(b, h, w.t())))
    w.requires_grad_(True)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = linear_relu(w, b, h.bfloat16())
    out.float().sum().backward()
    assert fused_calls == [] and w.grad is not None


def test_nerf_field_renders_the_same_with_and_without_the_fused_relu(fused_calls,
                                                                     monkeypatch) -> None:
    """The 4×64 field without autograd under bf16 autocast (an evaluation image's query):
    the same σ and rgb to the bit whether its four hidden layers and colour layer fuse
    their ReLU or not."""
    torch.manual_seed(0)
    f = NeRFField(depth=4, width=64, skip=-1, remap_width=64, colour_width=32, anneal_steps=0)
    xyz, t = torch.rand(4096, 3) * 2 - 1, torch.rand(4096, 1)
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        fused = f(xyz, t)
        assert len(fused_calls) == 5
        monkeypatch.setattr(lin, "_POINTWISE", None)
        plain = f(xyz, t)
    for a, b in zip(fused, plain):
        assert torch.equal(a, b)
