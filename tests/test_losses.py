"""The four losses against hand-computed values, ablation switches and log-space edge cases."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
import torch

from eventrecon.common.errors import InputError
from eventrecon.engine.losses import (
    LossConfig,
    acc_loss,
    event_loss,
    rgb_loss,
    sparsity_loss,
    sparsity_weight,
    total_loss,
)

EPS, THETA = 0.01, 0.5
RGB0 = torch.tensor([[0.1, 0.2, 0.3], [0.0, 1.0, 0.5]], dtype=torch.float64)
RGB1 = torch.tensor([[0.2, 0.2, 0.3], [0.0, 1.0, 0.25]], dtype=torch.float64)
MASK = torch.tensor([[1.0, 0, 0], [0, 0, 1.0]], dtype=torch.float64)  # R pixel, B pixel
E = torch.tensor([1.0, -2.0], dtype=torch.float64)


def test_event_loss_hand_computed() -> None:
    r0 = math.log(0.21 / 0.11) - 0.5 * 1.0       # ray 0, red channel
    r1 = math.log(0.26 / 0.51) - 0.5 * (-2.0)    # ray 1, blue channel
    expected = (r0**2 + r1**2) / 6               # 2 rays × 3 channels, masked zeros included
    got = event_loss(RGB0, RGB1, E, MASK, EPS, THETA)
    assert got.item() == pytest.approx(expected, rel=1e-12)
    assert expected == pytest.approx(0.0213254, abs=1e-7)


def test_event_loss_grey_mode_uses_log_of_channel_mean() -> None:
    m0, m1 = RGB0.mean(1).tolist(), RGB1.mean(1).tolist()
    expected = sum((math.log((b + EPS) / (a + EPS)) - THETA * e) ** 2
                   for a, b, e in zip(m0, m1, E.tolist())) / 2
    assert event_loss(RGB0, RGB1, E, None, EPS, THETA).item() == pytest.approx(expected, 1e-12)
    # An all-ones mask compares every channel instead (mean over N × 3).
    per_ch = (torch.log((RGB1 + EPS) / (RGB0 + EPS)) - THETA * E[:, None]) ** 2
    got = event_loss(RGB0, RGB1, E, torch.ones_like(RGB0), EPS, THETA)
    assert got.item() == pytest.approx(per_ch.mean().item(), rel=1e-12)


def test_acc_loss_hand_computed() -> None:
    ref = torch.tensor([[0.05, 0.5, 0.9], [0.3, 0.3, 0.1]], dtype=torch.float64)
    e_ref = torch.tensor([2.0, -1.0], dtype=torch.float64)
    r0 = math.log(0.21) - (math.log(0.06) + 0.5 * 2.0)
    r1 = math.log(0.26) - (math.log(0.11) + 0.5 * (-1.0))
    expected = (r0**2 + r1**2) / 6
    assert acc_loss(RGB1, ref, e_ref, MASK, EPS, THETA).item() == pytest.approx(expected, 1e-12)
    # A single-channel raw reference is the value of the channel the pixel sees.
    raw = torch.tensor([0.05, 0.1], dtype=torch.float64)
    assert acc_loss(RGB1, raw, e_ref, MASK, EPS, THETA).item() == pytest.approx(expected, 1e-12)


def test_rgb_loss_hand_computed() -> None:
    ref = torch.tensor([[0.1, 0.1, 0.1], [0.0, 0.5, 0.5]], dtype=torch.float64)
    expected = (0.1**2 + 0.1**2 + 0.2**2 + 0.0**2 + 0.5**2 + 0.25**2) / 6
    assert rgb_loss(RGB1, ref).item() == pytest.approx(expected, rel=1e-12)
    raw = torch.tensor([0.1, 0.5], dtype=torch.float64)  # R of ray 0, B of ray 1
    assert rgb_loss(RGB1, raw, MASK).item() == pytest.approx((0.1**2 + 0.25**2) / 2, 1e-12)
    with pytest.raises(InputError, match="raw_mask"):
        rgb_loss(RGB1, raw)


def test_sparsity_loss_and_ramp() -> None:
    ops = [torch.tensor([0.0, 1.0]), torch.tensor([0.25, 0.25]), torch.tensor([1.0, 1.0])]
    assert sparsity_loss(ops).item() == pytest.approx(0.5 + 0.25 + 1.0)
    assert sparsity_weight(0) == 0.0
    assert sparsity_weight(30000) == pytest.approx(1e-2 * (1 - math.exp(-1)), rel=1e-12)
    assert sparsity_weight(10**7) == pytest.approx(1e-2, rel=1e-12)
    assert sparsity_weight(5, lam=0.3, ramp=0) == 0.3


def _levels_and_batch(requires_grad: bool = False) -> tuple[list[dict], dict]:
    g = torch.Generator().manual_seed(0)
    levels = []
    for _ in range(2):  # coarse, fine
        lv = {k: torch.rand(8, 3, generator=g, dtype=torch.float64,
                            requires_grad=requires_grad)
              for k in ("rgb_t0", "rgb_t1", "rgb_ref")}
        for k in ("opacity_t0", "opacity_t1", "opacity_ref"):
            lv[k] = torch.rand(8, generator=g, dtype=torch.float64)
        levels.append(lv)
    rows, cols = torch.arange(8) // 4, torch.arange(8) % 4
    mask = torch.nn.functional.one_hot(rows % 2 + cols % 2, 3).double()
    batch = {"events": torch.randint(-3, 4, (8,), generator=g).float(),
             "events_ref": torch.randint(-3, 4, (8,), generator=g).float(),
             "ref_rgb": torch.rand(8, 3, generator=g, dtype=torch.float64), "mask": mask}
    return levels, batch


def test_total_loss_sums_levels_and_weights() -> None:
    levels, batch = _levels_and_batch()
    cfg = LossConfig()
    step = 12345
    out = total_loss(levels, batch, cfg, step)
    ev = sum(event_loss(l["rgb_t0"], l["rgb_t1"], batch["events"], batch["mask"], cfg.eps,
                        cfg.theta) for l in levels)
    ac = sum(acc_loss(l["rgb_t1"], batch["ref_rgb"], batch["events_ref"], batch["mask"],
                      cfg.eps, cfg.theta) for l in levels)
    rg = sum(rgb_loss(l["rgb_ref"], batch["ref_rgb"]) for l in levels)
    sp = sum(l[k].mean() for l in levels for k in ("opacity_t0", "opacity_t1", "opacity_ref"))
    lam = 1e-2 * (1 - math.exp(-step / 30000))
    expected = ev + ac + 0.01 * rg + lam * sp
    assert out["loss"].item() == pytest.approx(expected.item(), rel=1e-6)
    for k, v in [("event", ev), ("acc", ac), ("rgb", rg), ("sparsity", sp)]:
        assert out[k].item() == pytest.approx(v.item(), rel=1e-6)


def test_a_loss_mask_weights_the_photometric_terms_as_the_authors_img2mse() -> None:
    levels, batch = _levels_and_batch()
    w = torch.tensor([1.0, 0.0, 0.5, 1.0, 0.0, 0.25, 1.0, 0.75], dtype=torch.float64)
    cfg, step = LossConfig(), 12345
    plain = total_loss(levels, batch, cfg, step)
    out = total_loss(levels, {**batch, "weight": w}, cfg, step)

    def img2mse(x, y):        # the authors' utils.img2mse, written out: Σ w·d² / (Σw·C + 1e-6)
        return ((x - y) ** 2 * w[:, None]).sum() / (w.sum() * x.shape[-1] + 1e-6)

    m = batch["mask"]
    for key, expected in [
        ("event", sum(img2mse(m * (torch.log(lv["rgb_t1"] + cfg.eps)
                                   - torch.log(lv["rgb_t0"] + cfg.eps)),
                              m * cfg.theta * batch["events"][:, None]) for lv in levels)),
        ("acc", sum(img2mse(m * torch.log(lv["rgb_t1"] + cfg.eps),
                            m * (torch.log(batch["ref_rgb"] + cfg.eps)
                                 + cfg.theta * batch["events_ref"][:, None])) for lv in levels)),
        ("rgb", sum(img2mse(lv["rgb_ref"], batch["ref_rgb"]) for lv in levels))]:
        assert out[key].item() == pytest.approx(expected.item(), rel=1e-9)
    assert out["sparsity"].item() == plain["sparsity"].item()        # never weighted
    ones = total_loss(levels, {**batch, "weight": torch.ones(8, dtype=torch.float64)}, cfg, step)
    for key in ("event", "acc", "rgb"):       # all-ones weights: the plain means (to 1e-6)
        assert ones[key].item() == pytest.approx(plain[key].item(), rel=1e-6)
    raw = torch.rand(8, dtype=torch.float64)  # a raw reference: C = 1
    pred = (levels[0]["rgb_ref"] * m).sum(-1)
    assert rgb_loss(levels[0]["rgb_ref"], raw, m, w).item() == pytest.approx(
        ((pred - raw) ** 2 * w).sum().item() / (w.sum().item() + 1e-6), rel=1e-9)


@pytest.mark.parametrize("field,key", [("w_event", "event"), ("w_acc", "acc"),
                                       ("w_rgb", "rgb"), ("lam_sparsity", "sparsity")])
def test_each_ablation_switches_exactly_one_term(field: str, key: str) -> None:
    levels, batch = _levels_and_batch()
    cfg = LossConfig()
    full = total_loss(levels, batch, cfg, 50000)
    off = total_loss(levels, batch, replace(cfg, **{field: 0.0}), 50000)
    assert key not in off and key in full
    weight = {"event": 1.0, "acc": 1.0, "rgb": 0.01,
              "sparsity": sparsity_weight(50000)}[key]
    assert (full["loss"] - off["loss"]).item() == pytest.approx(weight * full[key].item(),
                                                                rel=1e-9)
    for other in {"event", "acc", "rgb", "sparsity"} - {key}:
        assert off[other].item() == full[other].item()


def test_disabled_term_is_not_computed() -> None:
    levels, batch = _levels_and_batch()
    del batch["events"]  # only L_event needs it
    out = total_loss(levels, batch, LossConfig(w_event=0.0), 0)
    assert "event" not in out and math.isfinite(out["loss"].item())
    with pytest.raises(KeyError):
        total_loss(levels, batch, LossConfig(), 0)


@pytest.mark.parametrize("eps", [1e-2, 3e-2])
def test_black_and_saturated_pixels_finite_values_and_gradients(eps: float) -> None:
    levels, batch = _levels_and_batch(requires_grad=True)
    for lv in levels:
        with torch.no_grad():
            lv["rgb_t0"][:4] = 0.0   # black
            lv["rgb_t1"][4:] = 1.0   # saturated
            lv["rgb_t1"][:2] = 0.0
            lv["rgb_ref"][::2] = 0.0
    batch["ref_rgb"][:3] = 0.0
    batch["ref_rgb"][3:5] = 1.0
    out = total_loss(levels, batch, LossConfig(eps=eps), 1000)
    out["loss"].backward()
    assert all(math.isfinite(v.item()) for v in out.values())
    # |L(a) − L(b)| ≤ log((1+ε)/ε) for a, b ∈ [0, 1]; events here are |E| ≤ 3.
    bound = (math.log((1 + eps) / eps) + THETA * 3) ** 2
    assert out["event"].item() <= 2 * bound and out["acc"].item() <= 2 * bound
    for lv in levels:
        for k in ("rgb_t0", "rgb_t1", "rgb_ref"):
            grad = lv[k].grad
            assert grad is not None and torch.isfinite(grad).all()
            # d/dI log(I + ε) ≤ 1/ε bounds every gradient.
            assert grad.abs().max().item() < 4 * (math.log((1 + eps) / eps) + 1.5) / eps


def test_config_validation() -> None:
    with pytest.raises(InputError, match="theta"):
        LossConfig(theta=0.0)
    with pytest.raises(InputError, match="eps"):
        LossConfig(eps=0.0)
    levels, batch = _levels_and_batch()
    with pytest.raises(InputError, match="weights"):
        total_loss(levels, batch, LossConfig(w_event=0, w_acc=0, w_rgb=0, lam_sparsity=0), 0)
