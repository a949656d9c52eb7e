"""The fused rank sums' shared checks (``test_cp_fused.py``, ``test_hex_fused.py``): a
factorised field with its fused pass and factor by factor; a pass split between two
threads against one."""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType

import pytest
import torch

from baselines.factorised import FEATURES
from eventrecon.sim.jit import GRAIN, parts
from eventrecon.sim.pipeline import torch_threads


def fused_and_by_factor(field: torch.nn.Module, module: ModuleType, name: str,
                        monkeypatch: pytest.MonkeyPatch, n: int = 300) -> list[tuple]:
    """``[(sigma, rgb, factor gradients)]`` of ``field`` at ``n`` random points on one
    thread: first as it is (checking that ``module.name``, its fused rank sum, served
    every call), then with that function declining, so that the factors are sampled one
    by one. The gradients are of ``Σσ + Σrgb``."""
    g = torch.Generator().manual_seed(3)
    xyz, t = torch.rand(n, 3, generator=g) * 2 - 1, torch.rand(n, 1, generator=g)
    out, served = [], []
    real = getattr(module, name)

    def spy(*args, **kwargs):
        served.append(real(*args, **kwargs))
        return served[-1]

    monkeypatch.setattr(module, name, spy)
    for fused in (True, False):
        if not fused:
            assert served and all(r is not None for r in served)   # the fused pass ran
            monkeypatch.setattr(module, name, lambda *a, **k: None)
        field.zero_grad(set_to_none=True)
        with torch_threads(1):
            sigma, rgb = field(xyz, t)
            (sigma.sum() + rgb.sum()).backward()
        out.append((sigma.detach(), rgb.detach(), [p.grad.clone() for p in field.grids.factors]))
    return out


def split_between_two_threads(module: ModuleType, rank_sum: Callable[[torch.Tensor], torch.Tensor],
                              params: list[torch.Tensor], coords: torch.Tensor,
                              monkeypatch: pytest.MonkeyPatch) -> dict[str, int]:
    """Check a fused rank sum ``rank_sum(coords) -> [N, F]`` split between two torch
    threads: the same values as on one, to the bit, and the gradients of ``params``
    exactly the sum of each half's one-thread gradient (the ranges scatter into their own
    copies, added once). Returns how often ``module``'s ``_forward_parts`` and
    ``_backward_parts`` ran on the two threads."""
    n = coords.shape[0]
    w = torch.randn(n, FEATURES, generator=torch.Generator().manual_seed(2), dtype=coords.dtype)

    def run(rows: slice) -> tuple[torch.Tensor, tuple[torch.Tensor, ...]]:
        out = rank_sum(coords[rows])
        return out.detach(), torch.autograd.grad((out * w[rows]).sum(), params)

    with torch_threads(1):
        one, _ = run(slice(None))
        halves = [run(slice(0, n // 2))[1], run(slice(n // 2, n))[1]]
    split = {k: [] for k in ("_forward_parts", "_backward_parts")}
    with monkeypatch.context() as m:
        for name, calls in split.items():
            kernel = getattr(module, name)
            m.setattr(module, name, lambda *a, c=calls, k=kernel: (c.append(1), k(*a))[1])
        with torch_threads(2):
            assert parts(n, GRAIN) == 2
            two, g_two = run(slice(None))
            with torch.no_grad():
                assert torch.equal(rank_sum(coords), one)
    assert torch.equal(two, one)
    for a, b0, b1 in zip(g_two, *halves):
        assert torch.equal(a, b0 + b1)
    return {k: len(v) for k, v in split.items()}
