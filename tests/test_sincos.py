"""The encoding's sine and cosine (``eventrecon.fields.sincos``): accurate to float32's
epsilon against float64, the same values whatever the layout, the threads or autograd,
and PyTorch's functions wherever the compiled pass does not apply."""

from __future__ import annotations

import math

import pytest
import torch

import eventrecon.fields.sincos as sc
from eventrecon.compiled import AVAILABLE
from eventrecon.fields.sincos import LIMIT, sin_cos

EPS = 2.0 ** -23
compiled_only = pytest.mark.skipif(not AVAILABLE, reason="numba not installed")


def _angles(n: int = 5000, f: int = 49, seed: int = 0) -> torch.Tensor:
    """Angles of every magnitude up to ``LIMIT``, and the quadrant boundaries."""
    g = torch.Generator().manual_seed(seed)
    scale = torch.logspace(-8, math.log10(LIMIT * 0.999), f)
    a = (torch.rand(n, f, generator=g) * 2 - 1) * scale
    k = torch.arange(-8000, 8000, 100, dtype=torch.float64)
    a[:k.numel(), 0] = (k * math.pi / 4).float()                 # multiples of π/4
    a[0, 1:4] = torch.tensor([0.0, -0.0, LIMIT * 0.9999])
    return a


def test_within_one_float32_epsilon_of_float64() -> None:
    """Absolute error at most one float32 epsilon (2⁻²³) for |A| < LIMIT, measured
    against float64 on the same float32 angles; and close to what torch gives."""
    a = _angles()
    s, c = sin_cos(a)
    assert s.dtype == c.dtype == torch.float32
    assert float((s.double() - torch.sin(a.double())).abs().max()) <= EPS
    assert float((c.double() - torch.cos(a.double())).abs().max()) <= EPS
    assert float((s - torch.sin(a)).abs().max()) <= 2 * EPS
    assert float((c - torch.cos(a)).abs().max()) <= 2 * EPS


@compiled_only
def test_any_layout_and_thread_count_gives_the_same_bits(monkeypatch) -> None:
    """Outputs written into column blocks of a wider tensor (its other columns left as
    they were), into bf16 blocks (the float32 values cast), on one range or two: the
    same values, element by element."""
    a = _angles(9000)
    s, c = sin_cos(a)
    wide = torch.full((a.shape[0], 3 + 2 * a.shape[1]), 7.0)
    sin_cos(a, wide[:, 3:3 + a.shape[1]], wide[:, 3 + a.shape[1]:])
    assert torch.equal(wide[:, 3:3 + a.shape[1]], s) and torch.equal(wide[:, 3 + a.shape[1]:], c)
    assert bool((wide[:, :3] == 7.0).all())
    half = torch.empty(a.shape, dtype=torch.bfloat16), torch.empty(a.shape, dtype=torch.bfloat16)
    sin_cos(a, *half)
    assert torch.equal(half[0], s.bfloat16()) and torch.equal(half[1], c.bfloat16())
    monkeypatch.setattr(sc, "parts", lambda n: 1)
    one = sin_cos(a)
    monkeypatch.setattr(sc, "parts", lambda n: 2)
    two = sin_cos(a)
    for x, y, z in zip(one, two, (s, c)):
        assert torch.equal(x, y) and torch.equal(x, z)


@compiled_only
def test_far_or_non_finite_angles_make_the_call_take_torch() -> None:
    """An angle at LIMIT or beyond, or not finite, anywhere in the call: every value is
    then ``torch.sin`` / ``torch.cos``'s (NaN where theirs is)."""
    for bad in (LIMIT, -1e6, float("inf"), float("nan")):
        a = _angles(300)
        a[17, 5] = bad
        s, c = sin_cos(a)
        assert torch.equal(torch.nan_to_num(s, 9.0), torch.nan_to_num(torch.sin(a), 9.0))
        assert torch.equal(torch.nan_to_num(c, 9.0), torch.nan_to_num(torch.cos(a), 9.0))


def test_autograd_gives_the_same_values_and_the_derivatives() -> None:
    """With autograd through the angles: the values of the call without it, and
    ``∂(Σ u·sin A + v·cos A)/∂A = u·cos A − v·sin A`` within float32's rounding of
    float64's."""
    a = _angles(500)
    u, v = torch.randn(a.shape), torch.randn(a.shape)
    plain = sin_cos(a)
    x = a.clone().requires_grad_(True)
    s, c = sin_cos(x)
    assert torch.equal(s.detach(), plain[0]) and torch.equal(c.detach(), plain[1])
    (u * s + v * c).sum().backward()
    want = u.double() * torch.cos(a.double()) - v.double() * torch.sin(a.double())
    bound = 4 * EPS * (u.abs() + v.abs()).double()
    assert x.grad is not None and bool(((x.grad.double() - want).abs() <= bound).all())
    with pytest.raises(ValueError, match="outputs given with autograd"):
        sin_cos(x, torch.empty(a.shape), torch.empty(a.shape))


def test_other_dtypes_are_torch_s() -> None:
    """float64 and bf16 angles take ``torch.sin`` and ``torch.cos`` as they are."""
    a = _angles(200)
    for dtype in (torch.float64, torch.bfloat16):
        s, c = sin_cos(a.to(dtype))
        assert torch.equal(s, torch.sin(a.to(dtype))) and torch.equal(c, torch.cos(a.to(dtype)))
