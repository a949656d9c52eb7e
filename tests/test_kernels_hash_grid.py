"""NGP's 4D hash encoding in compiled loops (:mod:`eventrecon.kernels.hash_grid`) against
its PyTorch reference: an encoding built with ``implementation="numba"`` against the same
encoding with ``"torch"`` (vectorised corners and ``embedding_bag``), at the CPU NGP's
sizes; a NaN coordinate; one and two threads; what the kernel declines."""

from __future__ import annotations

import re

import pytest
import torch
from test_hashgrid import _edge_points

import eventrecon.kernels.hash_grid as hash_grid
from baselines.ngp import HashEncoding
from eventrecon.common.errors import InputError
from eventrecon.kernels.jit import numba_threads, parts
from eventrecon.sim.pipeline import torch_threads


@pytest.fixture(autouse=True)
def _one_thread():
    """One torch thread (the kernel then runs its serial loops); the two-thread test asks
    for two inside."""
    with torch_threads(1):
        yield


def _paper_cpu_encoding(implementation: str) -> HashEncoding:
    """The CPU NGP's encoding (2^17 rows, space at twice the cells), a random table."""
    enc = HashEncoding(4, 8, 2, 17, 8, 2.0, 1e-4, 0, axis_scale=(2.0, 2.0, 2.0, 1.0),
                       implementation=implementation)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        enc.table.copy_(torch.rand(enc.table.shape, generator=g) * 2 - 1)
    return enc


def _count_calls(monkeypatch: pytest.MonkeyPatch, name: str) -> list[int]:
    """Count the calls of ``hash_grid.name`` (a compiled loop called from Python)."""
    calls: list[int] = []
    kernel = getattr(hash_grid, name)
    monkeypatch.setattr(hash_grid, name, lambda *a: (calls.append(1), kernel(*a))[1])
    return calls


def test_kernel_equals_the_reference_values_and_gradient(monkeypatch):
    """At the CPU NGP's sizes (a dense level and seven hashed ones), on points at and
    beyond the box: the same values to 2e-7, the same table gradient to 1e-6 relative;
    the compiled forward and scatter ran."""
    calls = [_count_calls(monkeypatch, k) for k in ("_encode", "_scatter")]
    enc, ref = _paper_cpu_encoding("numba"), _paper_cpu_encoding("torch")
    assert torch.equal(enc.table, ref.table)
    assert enc.dense[0] and not any(enc.dense[1:])
    u = _edge_points(6000, seed=5)
    wts = torch.randn(6000, 16, generator=torch.Generator().manual_seed(6))
    out = enc(u)
    (g,) = torch.autograd.grad((out * wts).sum(), enc.table)
    assert [len(c) for c in calls] == [1, 1]
    out_ref = ref(u)
    (g_ref,) = torch.autograd.grad((out_ref * wts).sum(), ref.table)
    assert [len(c) for c in calls] == [1, 1]                       # the reference: no kernel
    assert (out - out_ref).abs().max().item() <= 2e-7
    assert (g - g_ref).abs().max().item() <= 1e-6 * g_ref.abs().max().item()
    with torch.no_grad():                                           # no graph: the same bits
        assert torch.equal(enc(u), out.detach())


def test_a_nan_coordinate_reads_nan_and_sends_nothing():
    enc = _paper_cpu_encoding("numba")
    u = _edge_points(100, seed=7)
    u[3, 2] = float("nan")
    keep = torch.arange(100) != 3
    out = enc(u)
    assert out[3].isnan().all() and torch.isfinite(out[keep]).all()
    (g,) = torch.autograd.grad(out[keep].sum(), enc.table)
    (g_ref,) = torch.autograd.grad(enc(u[keep]).sum(), enc.table)
    assert torch.equal(g, g_ref)


def test_the_cases_the_kernel_declines():
    """``unsupported`` names what a call lacks (``None`` where the kernel applies);
    ``encode`` raises it."""
    enc = _paper_cpu_encoding("numba")
    u = _edge_points(50)
    table, plan = enc.table, enc.plan
    assert hash_grid.unsupported(table, u, plan) is None
    rows = f"a float32 table of {plan.rows} rows and 2 features"
    three = HashEncoding(3, 2, 2, 10, 4)                            # 3 input axes
    one_feature = HashEncoding(4, 2, 1, 10, 4)
    cases = [
        ((table, u.double(), plan), "coordinates [N, 4] in float32"),
        ((table, u[:, :3], plan), "coordinates [N, 4] in float32"),
        ((table[:-1], u, plan), rows),                              # not the plan's rows
        ((table.detach().double(), u, plan), rows),
        ((one_feature.table, u, one_feature.plan), "a float32 table of"),
        ((three.table, u[:, :3], three.plan), "4 input axes"),
        ((table, u.clone().requires_grad_(True), plan),
         "no gradient with respect to the coordinates"),
        ((table.to("meta"), u, plan), "tensors on the CPU"),
    ]
    for args, reason in cases:
        assert (hash_grid.unsupported(*args) or "").startswith(reason), reason
        if args[0].device.type != "meta":
            with pytest.raises(InputError, match=re.escape(f"encode: expected {reason}")):
                hash_grid.encode(*args)
    with torch.no_grad():                      # no gradient wanted: the kernel applies
        assert hash_grid.unsupported(table, u.clone().requires_grad_(True), plan) is None


def test_second_order_gradients_through_the_kernel_are_refused():
    """The kernel's scatter is not itself differentiable: a gradient of the gradient
    raises instead of ignoring it."""
    enc = _paper_cpu_encoding("numba")
    out = enc(_edge_points(64))
    (g,) = torch.autograd.grad(out.square().sum(), enc.table, create_graph=True)
    with pytest.raises(RuntimeError):
        g.sum().backward()


@pytest.mark.skipif(numba_threads() < 2, reason="numba has one thread here")
def test_the_same_bits_on_one_and_two_threads(monkeypatch):
    """Split between threads (points in the forward, levels in the gradient, which own
    disjoint table rows) the sums run in the same order: the same bits."""
    split = [_count_calls(monkeypatch, k) for k in ("_encode_parts", "_scatter_parts")]
    enc = _paper_cpu_encoding("numba")
    u = _edge_points(3 * 4096, seed=8)
    wts = torch.randn(u.shape[0], 16, generator=torch.Generator().manual_seed(9))
    runs = []
    for threads in (1, 2):
        with torch_threads(threads):
            assert parts(u.shape[0]) == threads
            out = enc(u)
            runs.append((out.detach(), torch.autograd.grad((out * wts).sum(), enc.table)[0]))
    assert torch.equal(runs[0][0], runs[1][0]) and torch.equal(runs[0][1], runs[1][1])
    assert [len(c) for c in split] == [1, 1]                        # the two-thread run split
