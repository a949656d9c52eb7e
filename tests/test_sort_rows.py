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
    sr._exchange(cols, sr.network(k))
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


def test_other_tensors_take_torch_sort() -> None:
    x = torch.rand(4, 6, dtype=torch.float64, requires_grad=True)
    assert torch.equal(sr.sort_rows(x), x.sort(dim=-1).values)
    y = torch.rand(2, 3, 5)
    assert torch.equal(sr.sort_rows(y), y.sort(dim=-1).values)
