"""LPIPS-Alex: equality with the `lpips` package on the same random trunk, weight sources.

The `lpips` package imports torchvision (not installed here); the test injects a minimal
stand-in whose ``models.alexnet(pretrained=...)`` returns our own trunk (same layers,
same random weights), so both implementations see identical parameters.
"""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest
import torch

from eventrecon.evaluation import lpips as lpips_alex
from eventrecon.evaluation import metrics
from eventrecon.evaluation.lpips import (
    ALEXNET_FILE,
    AlexNetTrunk,
    LPIPSAlex,
    LPIPSUnavailable,
    lpips_heads_path,
)
from eventrecon.evaluation.metrics import evaluate_images


@pytest.fixture(autouse=True)
def _isolated(monkeypatch, tmp_path):
    """Fresh network cache, empty torch hub, no env weights, downloads off."""
    lpips_alex._CACHE.clear()
    monkeypatch.setattr(metrics, "_WARNED", set())
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    monkeypatch.delenv(lpips_alex.WEIGHTS_ENV, raising=False)
    monkeypatch.setenv(lpips_alex.OFFLINE_ENV, "1")
    yield
    lpips_alex._CACHE.clear()


def _random_trunk(seed: int) -> AlexNetTrunk:
    g = torch.Generator().manual_seed(seed)
    trunk = AlexNetTrunk()
    with torch.no_grad():
        for p in trunk.parameters():
            p.copy_(torch.randn(p.shape, generator=g) * (2.0 / p[0].numel()) ** 0.5)
    return trunk


@pytest.fixture
def reference_lpips(monkeypatch):
    """Import the `lpips` package with a fake torchvision; yields (module, trunk)."""
    trunk = _random_trunk(1)
    models = types.ModuleType("torchvision.models")
    calls = []

    def alexnet(pretrained: bool = False, **kwargs):
        calls.append(pretrained)
        holder = types.SimpleNamespace(features=trunk.features)
        return holder

    models.alexnet = alexnet
    tv = types.ModuleType("torchvision")
    tv.models = models
    monkeypatch.setitem(sys.modules, "torchvision", tv)
    monkeypatch.setitem(sys.modules, "torchvision.models", models)
    before = set(sys.modules)
    import lpips  # noqa: PLC0415 (imported under the stand-in only)

    yield lpips, trunk, calls
    for name in set(sys.modules) - before:
        if name == "lpips" or name.startswith("lpips."):
            del sys.modules[name]


def test_equals_lpips_package_on_same_random_trunk(reference_lpips):
    lpips, trunk, calls = reference_lpips
    ref = lpips.LPIPS(net="alex", pretrained=True, pnet_rand=True, verbose=False)
    assert calls == [False]  # the package asked for a random (non-pretrained) trunk
    ours = LPIPSAlex()
    ours.load_heads(torch.load(lpips_heads_path(), map_location="cpu", weights_only=True))
    ours.net.load_state_dict(trunk.state_dict())
    g = torch.Generator().manual_seed(2)
    x0 = torch.rand(3, 3, 96, 112, generator=g) * 2 - 1
    x1 = (x0 + 0.3 * torch.randn(x0.shape, generator=g)).clamp(-1, 1)
    with torch.no_grad():
        want = ref(x0, x1).reshape(-1)
        got = ours(x0, x1)
    assert want.shape == got.shape == (3,)
    assert float(want.min()) > 1e-3  # a non-trivial distance
    torch.testing.assert_close(got, want, atol=1e-6, rtol=0)
    # the [0,1] convenience path (normalize=True in the package) agrees too
    with torch.no_grad():
        want01 = ref((x0 + 1) / 2, (x1 + 1) / 2, normalize=True).reshape(-1)
    torch.testing.assert_close(ours(x0, x1), want01, atol=1e-6, rtol=0)


def test_state_dict_keys_match_torchvision_features():
    keys = set(AlexNetTrunk().state_dict())
    want = {f"features.{i}.{w}" for i in (0, 3, 6, 8, 10) for w in ("weight", "bias")}
    assert keys == want


def _save_trunk(path, seed: int = 3):
    torch.save({**_random_trunk(seed).state_dict(), "classifier.1.weight": torch.zeros(2, 2)}, path)


def test_identical_images_give_zero_and_env_weights_are_used(monkeypatch, tmp_path):
    wpath = tmp_path / "alex.pth"
    _save_trunk(wpath)
    monkeypatch.setenv(lpips_alex.WEIGHTS_ENV, str(wpath))
    rng = np.random.default_rng(0)
    img = rng.random((2, 64, 64, 3))
    out = evaluate_images(img, img)
    assert out["lpips_note"] is None
    assert abs(out["lpips"]) < 1e-7
    other = np.clip(img + rng.normal(0, 0.2, img.shape), 0, 1)
    d = evaluate_images(other, img)["lpips"]
    net = lpips_alex.load_lpips_alex()
    t = lambda a: torch.as_tensor(a, dtype=torch.float32).permute(0, 3, 1, 2) * 2 - 1  # noqa: E731
    with torch.no_grad():
        direct = float(net(t(other), t(img)).mean())
    assert d == pytest.approx(direct, abs=1e-6) and d > 1e-3


def test_hub_cache_file_is_found(monkeypatch, tmp_path):
    ckpt = tmp_path / "torch_home" / "hub" / "checkpoints" / ALEXNET_FILE
    ckpt.parent.mkdir(parents=True)
    _save_trunk(ckpt)
    img = np.full((32, 32, 3), 0.4)
    assert evaluate_images(img, img)["lpips"] == pytest.approx(0.0, abs=1e-7)


def test_missing_weights_offline_gives_none_with_one_line_note(monkeypatch, caplog):
    def no_probe(*a, **k):  # an offline run must not touch the network
        raise AssertionError("download attempted while offline")

    monkeypatch.setattr(lpips_alex, "_reachable", no_probe)
    img = np.full((32, 32, 3), 0.4)
    with caplog.at_level("WARNING"):
        out = evaluate_images(img, img + 0.1)
    assert out["lpips"] is None
    note = out["lpips_note"]
    assert note and "\n" not in note and "downloads are off" in note
    assert out["psnr"] == pytest.approx(20.0, abs=1e-9)
    assert any("LPIPS unavailable" in r.message for r in caplog.records)


def test_missing_weights_unreachable_fails_fast(monkeypatch):
    monkeypatch.delenv(lpips_alex.OFFLINE_ENV)
    monkeypatch.delenv("CI", raising=False)
    probes = []
    monkeypatch.setattr(
        lpips_alex, "_reachable", lambda url, t: probes.append(t) or "URLError: no route"
    )
    with pytest.raises(LPIPSUnavailable, match="unreachable") as exc:
        lpips_alex.load_lpips_alex()
    assert "\n" not in str(exc.value) and probes == [5.0]
    # the failure is remembered: no second probe in the same process
    with pytest.raises(LPIPSUnavailable):
        lpips_alex.load_lpips_alex()
    assert probes == [5.0]


def test_bad_env_path_is_one_line(monkeypatch, tmp_path):
    monkeypatch.setenv(lpips_alex.WEIGHTS_ENV, str(tmp_path / "nope.pth"))
    out = evaluate_images(np.zeros((16, 16, 3)), np.zeros((16, 16, 3)))
    assert out["lpips"] is None and lpips_alex.WEIGHTS_ENV in out["lpips_note"]
