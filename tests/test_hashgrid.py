"""The 4D hash encoding against a slow reference, exactness at dense levels, index safety;
the compiled CPU loops (baselines.hash_cpu) against the eager tensor path."""

from __future__ import annotations

import pytest
import torch

from baselines import hash_cpu
from baselines.ngp import PRIMES, HashEncoding, NGPField, hash_encode_reference
from eventrecon.sim.jit import AVAILABLE, numba_threads, parts
from eventrecon.sim.pipeline import torch_threads


@pytest.fixture(params=["compiled", "eager"])
def path(request, monkeypatch):
    """Both implementations: the compiled loops (asserted to have served a call), and
    the tensor path."""
    if request.param == "compiled" and not AVAILABLE:
        pytest.skip("no numba")
    if request.param == "eager":
        monkeypatch.setattr(hash_cpu, "encode", lambda *a, **k: None)
        yield request.param
        return
    served = []
    encode = hash_cpu.encode
    monkeypatch.setattr(hash_cpu, "encode",
                        lambda *a, **k: (lambda r: (served.append(r is not None), r)[1])(
                            encode(*a, **k)))
    yield request.param
    assert any(served)


def _count_calls(monkeypatch, module, name: str) -> list[int]:
    """Count the calls of ``module.name`` (a compiled kernel called from Python)."""
    calls: list[int] = []
    kernel = getattr(module, name)
    monkeypatch.setattr(module, name, lambda *a: (calls.append(1), kernel(*a))[1])
    return calls


def _random_table(enc: HashEncoding, seed: int = 0) -> None:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        enc.table.copy_(torch.rand(enc.table.shape, generator=g) * 2 - 1)


def _edge_points(n: int, seed: int = 1) -> torch.Tensor:
    """Random points in [0,1]^4 plus the box corners/faces, and points slightly outside."""
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 4, generator=g)
    special = torch.tensor([0.0, 1.0, -1e-3, 1 + 1e-3, -0.5, 2.0, 1 - 1e-7])
    pick = torch.randint(0, len(special), (n // 2, 4), generator=g)
    mask = torch.rand(n // 2, 4, generator=g) < 0.5
    u[: n // 2] = torch.where(mask, special[pick], u[: n // 2])
    return u


def test_paper_configuration_levels():
    enc = HashEncoding()  # 8 levels, 2 features, 2^19, base 8, scale 2
    assert enc.resolutions == [8, 16, 32, 64, 128, 256, 512, 1024]
    # (R+1)^4 <= 2^19 only for R = 8 (6561) and 16 (83521); 33^4 = 1185921 > 524288
    assert enc.dense == [True, True] + [False] * 6
    assert enc.offsets[-1] == 9**4 + 17**4 + 6 * 2**19


def test_matches_slow_reference(path):
    """Vectorised encoding == explicit loops over levels and 16 corners, to 1e-6."""
    enc = HashEncoding(log2_table_size=16, n_levels=6, base_resolution=4, per_level_scale=1.7)
    _random_table(enc)
    u = _edge_points(3000)
    got, ref = enc(u), hash_encode_reference(enc, u)
    assert got.shape == (3000, 12)
    assert any(enc.dense) and not all(enc.dense)  # both code paths exercised
    assert (got - ref).abs().max().item() <= 1e-6


def test_a_dense_level_of_exactly_table_size_rows_matches_the_reference(path):
    """``(R+1)^4 = T``: the level is dense (rows summed, not hashed), on both paths."""
    enc = HashEncoding(log2_table_size=8, n_levels=3, base_resolution=3, per_level_scale=2.0)
    assert enc.dense == [True, False, False] and 4**4 == enc.table_size
    _random_table(enc)
    u = _edge_points(2000, seed=11)
    assert (enc(u) - hash_encode_reference(enc, u)).abs().max().item() <= 1e-6


def test_gradient_matches_reference(path):
    """The hand-written scatter-add backward equals autograd through the reference."""
    enc = HashEncoding(log2_table_size=12, n_levels=4, base_resolution=3)
    _random_table(enc)
    u = _edge_points(500)
    wts = torch.randn(500, 8, generator=torch.Generator().manual_seed(2))
    (g1,) = torch.autograd.grad((enc(u) * wts).sum(), enc.table)
    (g2,) = torch.autograd.grad((hash_encode_reference(enc, u) * wts).sum(), enc.table)
    assert (g1 - g2).abs().max().item() <= 1e-5


def test_dense_vertices_return_stored_features_exactly(path):
    enc = HashEncoding(log2_table_size=17, n_levels=2, base_resolution=8)  # R = 8, 16 dense
    _random_table(enc)
    g = torch.Generator().manual_seed(3)
    for lvl, r in enumerate(enc.resolutions):
        assert enc.dense[lvl]
        v = torch.randint(0, r + 1, (400, 4), generator=g)
        v[:8] = r  # the far corner of the box
        v[8:16] = 0
        out = enc(v.float() / r)[:, 2 * lvl : 2 * lvl + 2]
        row = sum(v[:, k] * (r + 1) ** k for k in range(4)) + enc.offsets[lvl]
        assert torch.equal(out, enc.table[row].detach())


def test_multilinear_function_reproduced_at_dense_levels():
    """Quadrilinear interpolation is exact for functions linear in each coordinate."""
    enc = HashEncoding(log2_table_size=17, n_levels=2, base_resolution=8, n_features=1)

    def f(u: torch.Tensor) -> torch.Tensor:
        return 1 + 2 * u[:, 0] - u[:, 1] + 0.5 * u[:, 2] * u[:, 3] + 3 * u.prod(-1)

    with torch.no_grad():
        for lvl, r in enumerate(enc.resolutions):
            ax = torch.arange(r + 1, dtype=torch.float64) / r
            grid = torch.stack(torch.meshgrid(ax, ax, ax, ax, indexing="ij"), -1)
            # dense row = v0 + (R+1) v1 + ... : axis 0 fastest -> permute to (v3, v2, v1, v0)
            vals = f(grid.permute(3, 2, 1, 0, 4).reshape(-1, 4))
            enc.table[enc.offsets[lvl] : enc.offsets[lvl + 1], 0] = vals.float()
    u = torch.rand(2000, 4, generator=torch.Generator().manual_seed(4))
    out = enc(u)
    for lvl in range(2):
        assert (out[:, lvl] - f(u.double()).float()).abs().max().item() <= 2e-6


def test_hash_indices_inside_table_at_edges():
    """Indices stay in [0, T_l) for coordinates at and beyond the box, at every level;
    a level whose (R+1)^4 equals T exactly is dense and reaches row T - 1."""
    enc = HashEncoding(log2_table_size=8, n_levels=5, base_resolution=3, per_level_scale=2.0)
    assert enc.resolutions[0] == 3 and enc.dense[0] and 4**4 == enc.table_size
    u = _edge_points(2000)
    u[0] = 1.0
    for kind in ("dense", "hash"):
        idx, w = (a.permute(1, 2, 0) for a in enc.corners(u, kind))   # [N, L_k, 16]
        levels = getattr(enc, f"{kind}_levels").tolist()
        for j, lvl in enumerate(levels):
            rows = idx[:, j] - enc.offsets[lvl]
            size = enc.offsets[lvl + 1] - enc.offsets[lvl]
            assert rows.min().item() >= 0 and rows.max().item() < size
        if kind == "dense":
            assert (idx[0, 0] - enc.offsets[0]).max().item() == enc.table_size - 1
        # weights are a partition of unity with no negative entries, even outside the box
        assert w.min().item() >= 0 and (w.sum(-1) - 1).abs().max().item() <= 1e-6


def test_hash_has_no_int32_overflow():
    """The far corner of the finest paper level: v_k * pi_k reaches ~3.8e12 > 2^31."""
    enc = HashEncoding()  # finest level R = 1024
    u = torch.ones(1, 4)
    idx = enc.corners(u, "hash")[0].permute(1, 2, 0)                  # [N, L_k, 16]
    r = enc.resolutions[-1]
    expect = 0
    for k in range(4):
        expect ^= r * PRIMES[k]  # python ints: exact
    expect %= enc.table_size
    corner = 15  # all offset bits set: vertex (R, R, R, R)
    assert idx[0, -1, corner].item() - enc.offsets[-2] == expect


def test_field_at_segment_and_box_edges_is_finite_and_clamped():
    f = NGPField(log2_table_size=14, n_levels=4)
    xyz = torch.tensor([[1.0, -1.0, 1.0], [1.05, -1.05, 1.5], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    t = torch.tensor([[0.0], [-0.01], [1.0], [1.2]])
    sigma, rgb = f(xyz, t)
    assert torch.isfinite(sigma).all() and torch.isfinite(rgb).all()
    assert (sigma >= 0).all() and ((rgb >= 0) & (rgb <= 1)).all()
    # outside the box the field is the boundary value (coordinates clamped)
    assert torch.equal(sigma[0], sigma[1])
    assert torch.equal(sigma[2], f(xyz[3:], torch.ones(1, 1))[0][0])


@pytest.mark.slow
def test_compiled_encoder_matches_eager():
    enc = HashEncoding(log2_table_size=14, n_levels=4)
    _random_table(enc)
    u = _edge_points(1000)
    eager = enc(u)
    enc.use_compiled = True
    assert (enc(u) - eager).abs().max().item() <= 1e-6


def _paper_cpu_encoding() -> HashEncoding:
    """The CPU NGP's encoding (2^17 rows, space at twice the cells), a random table."""
    enc = HashEncoding(4, 8, 2, 17, 8, 2.0, 1e-4, 0, axis_scale=(2.0, 2.0, 2.0, 1.0))
    _random_table(enc)
    return enc


@pytest.mark.skipif(not AVAILABLE, reason="no numba")
def test_compiled_loops_equal_the_eager_path_values_and_gradient(monkeypatch):
    """At the CPU NGP's sizes (a dense level and seven hashed ones), on points at and
    beyond the box: the same values to 2e-7, the same table gradient to 1e-6 relative."""
    enc = _paper_cpu_encoding()
    assert enc.dense[0] and not any(enc.dense[1:])
    u = _edge_points(6000, seed=5)
    wts = torch.randn(6000, 16, generator=torch.Generator().manual_seed(6))
    out, (g,) = enc(u), torch.autograd.grad((enc(u) * wts).sum(), enc.table)
    monkeypatch.setattr(hash_cpu, "encode", lambda *a, **k: None)
    ref, (g_ref,) = enc(u), torch.autograd.grad((enc(u) * wts).sum(), enc.table)
    assert (out - ref).abs().max().item() <= 2e-7
    assert (g - g_ref).abs().max().item() <= 1e-6 * g_ref.abs().max().item()
    assert hash_cpu.supported(enc.table, u, enc.plan)
    assert not hash_cpu.supported(enc.table, u.double(), enc.plan)
    assert not hash_cpu.supported(enc.table[:-1], u, enc.plan)         # not the plan's rows


@pytest.mark.skipif(not AVAILABLE, reason="no numba")
def test_compiled_loops_a_nan_coordinate_reads_nan_and_sends_nothing():
    enc = _paper_cpu_encoding()
    u = _edge_points(100, seed=7)
    u[3, 2] = float("nan")
    out = enc(u)
    assert out[3].isnan().all() and torch.isfinite(out[torch.arange(100) != 3]).all()
    (g,) = torch.autograd.grad(out[torch.arange(100) != 3].sum(), enc.table)
    keep = torch.arange(100) != 3
    (g_ref,) = torch.autograd.grad(enc(u[keep]).sum(), enc.table)
    assert torch.equal(g, g_ref)


@pytest.mark.skipif(numba_threads() < 2, reason="numba has one thread here")
def test_compiled_loops_give_the_same_bits_on_one_and_two_threads(monkeypatch):
    """Split between threads (points in the forward, levels in the gradient, which own
    disjoint table rows) the sums run in the same order: the same bits."""
    split = [_count_calls(monkeypatch, hash_cpu, k) for k in ("_encode_parts", "_scatter_parts")]
    enc = _paper_cpu_encoding()
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
