"""``eventrecon.render.sort_rows``: a sorting network against ``torch.sort``."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from eventrecon.render import sort_rows as sr

pytestmark = pytest.mark.skipif(not sr.AVAILABLE, reason="needs numba")


@pytest.mark.parametrize("k", [*range(1, 18), 31, 32, 33, 64, 100, 128])
def test_the_values_of_torch_sort_bit_for_bit(k: int) -> None:
    g = torch.Generator().manual_seed(k)
    x = torch.rand(300, k, generator=g)
    x[::7, : k // 2] = 0.5                               # ties
    x[1::5] = -x[1::5] * 1e-30                           # negatives and tiny values
    out = sr.sort_rows(x)
    assert out.is_contiguous() and out.shape == x.shape
    assert torch.equal(out, x.sort(dim=-1).values)


@pytest.mark.parametrize("k", range(1, 13))
def test_the_network_sorts_every_zero_one_row(k: int) -> None:
    """The 0-1 principle: a network that sorts all 2^k rows of 0s and 1s sorts every row."""
    rows = np.array(list(itertools.product((0.0, 1.0), repeat=k)), dtype=np.float32)
    cols = np.ascontiguousarray(rows.T)
    sr._exchange(cols, sr.network(k), 0, cols.shape[1])
    assert np.array_equal(cols.T, np.sort(rows, axis=1))


def test_network_size_is_batchers() -> None:
    """Batcher's count for a power of two ``P``: ``P/4 · log P (log P − 1) + P − 1``."""
    for log in range(1, 8):
        p = 1 << log
        assert len(sr.network(p)) == p // 4 * log * (log - 1) + p - 1
        assert all(i < j < p for i, j in sr.network(p))


def test_split_between_two_threads_the_same(monkeypatch: pytest.MonkeyPatch) -> None:
    x = torch.rand(5000, 32, generator=torch.Generator().manual_seed(1))
    original, called = sr._exchange_parts, []

    def spy(*args):
        called.append(args[2])
        return original(*args)

    monkeypatch.setattr(sr, "parts", lambda n, grain: 2)
    monkeypatch.setattr(sr, "_exchange_parts", spy)
    assert torch.equal(sr.sort_rows(x), x.sort(dim=-1).values)
    assert called == [2]


def test_other_tensors_take_torch_sort(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*args):
        raise AssertionError("the compiled passes ran")

    monkeypatch.setattr(sr, "_exchange", refuse)
    monkeypatch.setattr(sr, "_exchange_parts", refuse)
    for x in (torch.rand(4, 6, dtype=torch.float64, requires_grad=True),
              torch.rand(2, 3, 5), torch.rand(4, 6).bfloat16()):
        assert torch.equal(sr.sort_rows(x), x.sort(dim=-1).values)


@pytest.mark.parametrize("shape", [(0, 32), (1, 32), (7, 0), (1, 1)])
def test_empty_and_single_rows_leave_the_input_as_it_was(shape: tuple[int, int]) -> None:
    x = torch.rand(shape, generator=torch.Generator().manual_seed(2))
    before = x.clone()
    out = sr.sort_rows(x)
    assert torch.equal(out, before.sort(dim=-1).values) and torch.equal(x, before)
    assert out.data_ptr() != x.data_ptr() or x.numel() == 0


def test_a_column_major_input_is_copied_not_sorted_in_place() -> None:
    y = torch.rand(32, 40, generator=torch.Generator().manual_seed(3))
    x = y.t()                                            # [40, 32], its transpose contiguous
    before = y.clone()
    assert torch.equal(sr.sort_rows(x), x.sort(dim=-1).values)
    assert torch.equal(y, before)


def test_float64_and_signed_zeros_keep_every_value() -> None:
    g = torch.Generator().manual_seed(4)
    x = torch.rand(200, 24, generator=g, dtype=torch.float64)
    assert torch.equal(sr.sort_rows(x), x.sort(dim=-1).values)
    z = torch.tensor([[0.0, -0.0, 1.0, -0.0, 0.0, -1.0]] * 3)
    out = sr.sort_rows(z)
    assert torch.equal(out, z.sort(dim=-1).values)       # ±0 compare equal
    bits = lambda t: sorted(t.view(torch.int32).reshape(-1).tolist())  # noqa: E731
    assert bits(out) == bits(z)                          # and no −0 became +0


def test_a_nan_stays_a_member_of_its_row() -> None:
    x = torch.tensor([[0.3, float("nan"), 0.1, 0.2]])
    out = sr.sort_rows(x)
    assert int(out.isnan().sum()) == 1
    assert sorted(out[~out.isnan()].tolist()) == sorted(x[~x.isnan()].tolist())
