"""The 4D hash encoding against a slow reference, exactness at dense levels, index
safety: the PyTorch reference (``implementation="torch"``) and the default (``"auto"``:
the compiled loops of :mod:`eventrecon.kernels.hash_grid` where they apply, asserted to
have served). The compiled loops against the reference: ``test_kernels_hash_grid.py``."""

from __future__ import annotations

import pytest
import torch

import eventrecon.kernels.hash_grid as hash_grid
from baselines.ngp import PRIMES, HashEncoding, NGPField, hash_encode_reference


@pytest.fixture(params=["torch", "auto"])
def implementation(request, monkeypatch):
    """Both implementations: ``torch`` (the kernel never called) and ``auto`` (the kernel
    asserted to have served a call)."""
    calls: list[int] = []
    encode = hash_grid.encode
    monkeypatch.setattr(hash_grid, "encode",
                        lambda *a, **k: (calls.append(1), encode(*a, **k))[1])
    yield request.param
    assert bool(calls) == (request.param == "auto")


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


def test_matches_slow_reference(implementation):
    """Vectorised encoding == explicit loops over levels and 16 corners, to 1e-6."""
    enc = HashEncoding(log2_table_size=16, n_levels=6, base_resolution=4, per_level_scale=1.7,
                       implementation=implementation)
    _random_table(enc)
    u = _edge_points(3000)
    got, ref = enc(u), hash_encode_reference(enc, u)
    assert got.shape == (3000, 12)
    assert any(enc.dense) and not all(enc.dense)  # both code paths exercised
    assert (got - ref).abs().max().item() <= 1e-6


def test_a_dense_level_of_exactly_table_size_rows_matches_the_reference(implementation):
    """``(R+1)^4 = T``: the level is dense (rows summed, not hashed), on both paths."""
    enc = HashEncoding(log2_table_size=8, n_levels=3, base_resolution=3, per_level_scale=2.0,
                       implementation=implementation)
    assert enc.dense == [True, False, False] and 4**4 == enc.table_size
    _random_table(enc)
    u = _edge_points(2000, seed=11)
    assert (enc(u) - hash_encode_reference(enc, u)).abs().max().item() <= 1e-6


def test_gradient_matches_reference(implementation):
    """The table gradient (the kernel's scatter, or autograd through ``embedding_bag``)
    equals autograd through the slow reference."""
    enc = HashEncoding(log2_table_size=12, n_levels=4, base_resolution=3,
                       implementation=implementation)
    _random_table(enc)
    u = _edge_points(500)
    wts = torch.randn(500, 8, generator=torch.Generator().manual_seed(2))
    (g1,) = torch.autograd.grad((enc(u) * wts).sum(), enc.table)
    (g2,) = torch.autograd.grad((hash_encode_reference(enc, u) * wts).sum(), enc.table)
    assert (g1 - g2).abs().max().item() <= 1e-5


def test_dense_vertices_return_stored_features_exactly(implementation):
    enc = HashEncoding(log2_table_size=17, n_levels=2, base_resolution=8,   # R = 8, 16 dense
                       implementation=implementation)
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
