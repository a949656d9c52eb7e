"""The one switch between the PyTorch references and the compiled kernels
(:mod:`eventrecon.kernels`, a backbone's ``implementation``): ``"torch"`` never calls a
kernel, ``"auto"`` calls it where it applies and otherwise gives the reference's bits,
``"numba"`` raises an error naming ``implementation`` where it cannot apply; unknown
values are refused; ``model.implementation`` of ``conf/model/*.yaml`` reaches the field."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch import Tensor, nn

import eventrecon.kernels.factor_grids as factor_grids
import eventrecon.kernels.hash_grid as hash_grid
from baselines import HashEncoding, HexPlaneField, NGPField, TensoRFCPField
from eventrecon.common.errors import InputError
from eventrecon.kernels import IMPLEMENTATIONS, resolve, use_kernel
from eventrecon.sim.pipeline import torch_threads

CONF = Path(__file__).resolve().parents[1] / "conf"
KINDS = ["ngp", "tensorf_cp", "hexplane"]
#: Each backbone's kernel, as its module calls it.
KERNELS = {"ngp": (hash_grid, "encode"), "tensorf_cp": (factor_grids, "cp_rank_sum"),
           "hexplane": (factor_grids, "hex_rank_sum")}


@pytest.fixture(autouse=True)
def _one_thread():
    with torch_threads(1):
        yield


class _KernelCalled(Exception):
    """Raised by a kernel patched to refuse every call."""


def _refuse(*args, **kwargs):
    raise _KernelCalled


def _small(kind: str, implementation: str) -> nn.Module:
    if kind == "ngp":
        return NGPField(log2_table_size=14, n_levels=4, base_resolution=4,
                        implementation=implementation)
    if kind == "tensorf_cp":
        return TensoRFCPField(rank=4, resolution_init=(8, 8, 8, 6),
                              resolution_final=(8, 8, 8, 6), n_stages=1,
                              implementation=implementation)
    return HexPlaneField(rank=4, resolution=(9, 9, 9, 6), implementation=implementation)


def _points(n: int, seed: int = 0) -> tuple[Tensor, Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=g) * 2 - 1, torch.rand(n, 1, generator=g)


def _step(field: nn.Module, xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor, list[Tensor]]:
    """``(σ, rgb, the parameters' gradients of Σσ + Σrgb)``."""
    field.zero_grad(set_to_none=True)
    sigma, rgb = field(xyz, t)
    (sigma.sum() + rgb.sum()).backward()
    return sigma.detach(), rgb.detach(), [p.grad.clone() for p in field.parameters()]


@pytest.mark.parametrize("kind", KINDS)
def test_torch_never_calls_a_kernel(kind, monkeypatch):
    """With the kernel patched to raise, ``"torch"`` trains and asks the density alone
    (finite σ, rgb and gradients), while ``"auto"`` calls that very function."""
    monkeypatch.setattr(*KERNELS[kind], _refuse)
    xyz, t = _points(200)
    field = _small(kind, "torch")
    sigma, rgb, grads = _step(field, xyz, t)
    assert torch.isfinite(sigma).all() and torch.isfinite(rgb).all()
    assert all(torch.isfinite(g).all() for g in grads)
    with torch.no_grad():
        assert torch.isfinite(field.density_only(xyz, t)).all()
    with pytest.raises(_KernelCalled):
        _small(kind, "auto")(xyz, t)


@pytest.mark.parametrize("kind", KINDS)
def test_auto_where_the_kernel_applies_agrees_with_torch(kind, monkeypatch):
    """The same field under ``"auto"`` (the kernel, counted) and ``"torch"``: σ, rgb and
    every gradient equal to rounding."""
    calls: list[int] = []
    module, name = KERNELS[kind]
    kernel = getattr(module, name)
    monkeypatch.setattr(module, name, lambda *a, **k: (calls.append(1), kernel(*a, **k))[1])
    xyz, t = _points(300, 1)
    auto = _step(_small(kind, "auto"), xyz, t)
    assert calls == [1]
    ref = _step(_small(kind, "torch"), xyz, t)
    assert calls == [1]
    for a, b in zip([auto[0], auto[1], *auto[2]], [ref[0], ref[1], *ref[2]]):
        assert (a - b).abs().max().item() <= 1e-5 * max(1.0, b.abs().max().item())


@pytest.mark.parametrize("kind", ["tensorf_cp", "hexplane"])
def test_auto_where_the_kernel_does_not_apply_is_the_reference(kind, monkeypatch):
    """Coordinates that need a gradient (and, for the factors, float64 coordinates of a
    float32 field): ``"auto"`` does not call the kernel and gives the reference's bits,
    with the coordinates' gradient."""
    monkeypatch.setattr(*KERNELS[kind], _refuse)
    xyz, t = _points(100, 2)
    auto, ref = _small(kind, "auto"), _small(kind, "torch")
    for x in (xyz.clone().requires_grad_(True), xyz.double()):
        outs = []
        for f in (auto, ref):
            xi = x.detach().clone().requires_grad_(x.requires_grad)
            sigma, rgb = f(xi, t)
            if xi.requires_grad:
                (sigma.sum() + rgb.sum()).backward()
            outs.append((sigma, rgb, xi.grad))
        (s1, c1, g1), (s2, c2, g2) = outs
        assert torch.equal(s1, s2) and torch.equal(c1, c2)
        if x.requires_grad:
            assert g1 is not None and torch.equal(g1, g2) and g1.abs().sum() > 0


def _message(needs: str) -> str:
    return ("conf/model: implementation: expected auto or torch where the numba kernel does "
            f"not apply (it needs {needs}), got numba")


@pytest.mark.parametrize("kind", ["tensorf_cp", "hexplane"])
def test_numba_where_the_kernel_cannot_apply_raises_naming_implementation(kind):
    """Coordinates that need a gradient, float64 coordinates of a float32 field: one
    :class:`InputError` naming ``implementation`` and what the kernel needs. Without a
    gradient wanted, the kernel applies."""
    field = _small(kind, "numba")
    xyz, t = _points(50, 3)
    with pytest.raises(InputError) as e:
        field(xyz.clone().requires_grad_(True), t)
    assert str(e.value) == _message("no gradient with respect to the coordinates")
    with pytest.raises(InputError) as e:
        field(xyz.double(), t)
    assert str(e.value) == _message("factors and coordinates of one dtype, float32 or float64")
    with torch.no_grad():
        sigma, rgb = field(xyz.clone().requires_grad_(True), t)
    assert torch.isfinite(sigma).all() and torch.isfinite(rgb).all()


def test_numba_hexplane_factors_too_large_for_the_cache_raise(monkeypatch):
    monkeypatch.setattr(factor_grids, "MAX_BYTES", 1024)
    field = _small("hexplane", "numba")
    with pytest.raises(InputError) as e:
        field(*_points(10))
    assert str(e.value) == _message("factors of at most 1024 bytes in all (they must stay in "
                                    "cache)")
    auto = _small("hexplane", "auto")                    # the reference serves instead
    assert torch.isfinite(auto(*_points(10))[0]).all()


def test_numba_hash_encoding_where_the_kernel_cannot_apply_raises_naming_implementation():
    """A float64 table, one feature per level: one :class:`InputError` naming
    ``implementation``; ``"auto"`` then gives the reference's values."""
    u = torch.rand(40, 4, generator=torch.Generator().manual_seed(4))
    enc = HashEncoding(n_levels=3, log2_table_size=10, base_resolution=4,
                       implementation="numba").double()
    with pytest.raises(InputError) as e:
        enc(u)
    assert str(e.value) == _message(f"a float32 table of {enc.plan.rows} rows and 2 features")
    one = HashEncoding(n_levels=3, n_features=1, log2_table_size=10, base_resolution=4,
                       implementation="numba")
    with pytest.raises(InputError, match="implementation: expected auto or torch"):
        one(u)
    for cast in (lambda m: m.double(), lambda m: m):
        auto = cast(HashEncoding(n_levels=3, n_features=1, log2_table_size=10,
                                 base_resolution=4, implementation="auto"))
        ref = cast(HashEncoding(n_levels=3, n_features=1, log2_table_size=10,
                                base_resolution=4, implementation="torch"))
        assert torch.equal(auto(u), ref(u))


def test_ngp_coordinates_get_no_gradient_under_either_implementation():
    """The hash encoding differentiates its table, not its coordinates (no loss of the
    method needs them): coordinates that require a gradient get none, and ``"numba"``
    serves them."""
    xyz, t = _points(30, 5)
    for impl in ("torch", "auto", "numba"):
        x = xyz.clone().requires_grad_(True)
        f = _small("ngp", impl)
        sigma, rgb = f(x, t)
        (sigma.sum() + rgb.sum()).backward()
        assert x.grad is None and f.encoding.table.grad.abs().sum() > 0


@pytest.mark.parametrize("value", ["fast", "Numba", "", "compiled"])
def test_unknown_implementations_are_refused(value):
    assert IMPLEMENTATIONS == ("auto", "torch", "numba")
    assert [resolve(v) for v in IMPLEMENTATIONS] == list(IMPLEMENTATIONS)
    expected = f"conf/model: implementation: expected auto, torch or numba, got {value}"
    with pytest.raises(InputError) as e:
        resolve(value)
    assert str(e.value) == expected
    with pytest.raises(InputError, match="implementation: expected auto, torch or numba"):
        use_kernel(value, None)
    for kind in KINDS:
        with pytest.raises(InputError) as e:
            _small(kind, value)
        assert str(e.value) == expected


def test_use_kernel_decides_as_documented():
    assert use_kernel("auto", None) and use_kernel("numba", None)
    assert not use_kernel("auto", "tensors on the CPU")
    assert not use_kernel("torch", None) and not use_kernel("torch", "tensors on the CPU")
    with pytest.raises(InputError) as e:
        use_kernel("numba", "tensors on the CPU")
    assert str(e.value) == _message("tensors on the CPU")


def _implementation(field: nn.Module) -> str:
    return field.encoding.implementation if isinstance(field, NGPField) else field.implementation


@pytest.mark.parametrize("name", KINDS)
def test_the_config_key_reaches_the_field(name, monkeypatch):
    """``model.implementation`` (``auto`` in every ``conf/model/*.yaml``) reaches the
    field built by ``build_field`` (hydra's compose, the run's instantiate); with
    ``torch`` the field runs with its kernel patched to raise; an unknown value is one
    error naming the key."""
    from hydra import compose, initialize_config_dir

    from eventrecon.engine.build import build_field

    assert "\nimplementation: auto " in (CONF / "model" / f"{name}.yaml").read_text()
    models = {}
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        for value in (None, *IMPLEMENTATIONS, "fast"):
            over = [f"model={name}", "scale=cpu"]
            if value is not None:
                over.append(f"model.implementation={value}")
            models[value] = compose(config_name="config", overrides=over).model
    assert models[None].implementation == "auto"
    for value in IMPLEMENTATIONS:
        assert _implementation(build_field(models[value])) == value
    assert _implementation(build_field(models[None])) == "auto"
    with pytest.raises(InputError, match="implementation: expected auto, torch or numba, "
                                         "got fast"):
        build_field(models["fast"])
    monkeypatch.setattr(*KERNELS[name], _refuse)
    field = build_field(models["torch"])
    sigma, rgb = field(*_points(20, 6))
    assert sigma.shape == (20,) and torch.isfinite(rgb).all()
    with pytest.raises(_KernelCalled):
        build_field(models["auto"])(*_points(20, 6))
