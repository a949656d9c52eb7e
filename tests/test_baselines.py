"""The backbone zoo: grid helpers, growth, schedules, gradients, fitting, edge cases, bf16."""

from __future__ import annotations

from pathlib import Path

import lightning.pytorch as pl
import pytest
import torch
from torch import Tensor, nn

from baselines import CylinderAnneal, GrowthPlan, HexPlaneField, NGPField, TensoRFCPField
from baselines.factorised import FactorisedField
from baselines.grids import (
    geometric_resolutions,
    sample_grid,
    sample_grid_reference,
    total_variation,
    upsample_grid,
)
from baselines.hexplane import PAIRS

CONF = Path(__file__).resolve().parents[1] / "conf"


@pytest.fixture(autouse=True)
def _one_thread():
    """One intra-op thread: the test machine is shared, and OpenMP spinning on an
    oversubscribed 2-core box is ~10x slower than one thread."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def _small(kind: str, **kw) -> nn.Module:
    if kind == "ngp":
        return NGPField(log2_table_size=14, n_levels=4, base_resolution=4, **kw)
    cls = TensoRFCPField if kind == "tensorf_cp" else HexPlaneField
    kw.setdefault("resolution_init", (8, 8, 8, 6))
    kw.setdefault("resolution_final", (15, 15, 15, 11))
    return cls(rank=4, n_growth=kw.pop("n_growth", 1), **kw)


KINDS = ["ngp", "tensorf_cp", "hexplane"]


def _points(n: int, seed: int) -> tuple[Tensor, Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=g) * 2 - 1, torch.rand(n, 1, generator=g)


# ---------------------------------------------------------------- grid helpers
@pytest.mark.parametrize("shape", [(3, 7), (3, 5, 9), (2, 4, 5, 6)])
def test_sample_grid_matches_explicit_gather(shape):
    g = torch.Generator().manual_seed(0)
    grid = torch.randn(shape, generator=g)
    coords = torch.rand(500, len(shape) - 1, generator=g) * 2.2 - 1.1  # some outside
    coords[:4] = torch.tensor([-1.0, 1.0, 1.0, -1.0])[:, None]
    got, ref = sample_grid(grid, coords), sample_grid_reference(grid, coords)
    assert got.shape == (shape[0], 500)
    assert (got - ref).abs().max().item() <= 1e-6
    # border extension: beyond the box equals the boundary value
    assert torch.allclose(sample_grid(grid, coords.clamp(-1, 1)), got, atol=1e-6)


def test_geometric_resolutions_and_plan():
    res = geometric_resolutions((16, 16, 16, 16), (500, 500, 500, 24), 10)
    assert res[0] == (16,) * 4 and res[-1] == (500, 500, 500, 24) and len(res) == 11
    ratios = [b[0] / a[0] for a, b in zip(res, res[1:])]
    assert max(ratios) - min(ratios) < 0.05  # geometric: constant ratio (500/16)^(1/10) = 1.41
    plan = GrowthPlan((16,) * 4, (500, 500, 500, 24), 10, 0.2)
    assert plan.steps(10_000) == list(range(200, 2001, 200))  # 10 steps over 2e3 of 1e4
    assert plan.resolution_at(0, 10_000) == res[0] and plan.resolution_at(1999, 10_000) == res[9]
    assert plan.resolution_at(2000, 10_000) == res[10]


def test_total_variation_known_value():
    grid = torch.zeros(1, 3, 3)
    grid[0, 1, 1] = 1.0  # one bump: 4 unit differences in each of 6 pairs per axis
    assert total_variation(grid).item() == pytest.approx(2 * 2 / 6)


def _upsample_bound(grid: Tensor, size: tuple[int, ...]) -> Tensor:
    """Per-channel bound on |old interpolant - new interpolant|:
    sum_k (h'_k / 4 h_k) max |second difference along k| (a kink of slope jump s inside
    a fine cell of width h' is interpolated with error <= h' s / 4; bilinear = 1D in x
    then in y, and interpolation never increases the max norm)."""
    bound = torch.zeros(grid.shape[0])
    for k, (r, rn) in enumerate(zip(grid.shape[1:], size)):
        if r >= 3:
            d2 = grid.diff(n=2, dim=k + 1).abs().flatten(1).amax(1)
            bound += (r - 1) / (rn - 1) / 4 * d2
    return bound


@pytest.mark.parametrize("shape,size", [((4, 16), (23,)), ((4, 16, 12), (22, 17)),
                                        ((3, 16, 16), (31, 31))])
def test_upsample_error_within_bound(shape, size):
    g = torch.Generator().manual_seed(1)
    grid = torch.randn(shape, generator=g)
    new = upsample_grid(grid, size)
    x = torch.rand(4000, len(size), generator=g) * 2 - 1
    err = (sample_grid(grid, x) - sample_grid(new, x)).abs().amax(1)
    exact = all((rn - 1) % (r - 1) == 0 for r, rn in zip(shape[1:], size))
    bound = torch.full_like(err, 1e-5) if exact else _upsample_bound(grid, size) + 1e-5
    assert (err <= bound).all(), (err, bound)
    if not exact:  # the bound is not vacuous: the error reaches a good part of it
        assert (err / bound).max() > 0.2


@pytest.mark.parametrize("kind", ["tensorf_cp", "hexplane"])
def test_field_growth_changes_function_within_bound(kind):
    """Raw density sum_groups sum_r prod_j g_jr: with |g_jr| <= M_jr and a per-factor
    perturbation <= D_jr the change is <= sum (prod (M + D) - prod M); sigma = exp(raw)
    so |d sigma| / sigma <= exp(bound) - 1. Exact grids (R' - 1 = 2 (R - 1)) agree to 1e-5."""
    f: FactorisedField = _small(kind, n_growth=1, init_scale=0.5)
    xyz, t = _points(3000, 2)
    with torch.no_grad():
        for p in f.grids.factors:  # make the time factors vary too
            p.add_(0.3 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())))
        s0, c0 = f(xyz, t)
        target = (15, 15, 15, 11)  # from (8, 8, 8, 6): 14 = 2 * 7, 10 = 2 * 5 -> exact
        bounds = [_upsample_bound(p, [target[a] for a in ax])
                  for p, ax in zip(f.grids.factors, f.grids.axes)]
        maxes = [p.abs().flatten(1).amax(1) for p in f.grids.factors]
        f.upsample(target)
        s1, c1 = f(xyz, t)
        assert ((s1 - s0).abs() / s0).max().item() <= 1e-5
        assert (c1 - c0).abs().max().item() <= 1e-5
        # a non-nested growth step: bounded
        target2 = (21, 19, 20, 16)
        bounds = [_upsample_bound(p, [target2[a] for a in ax])
                  for p, ax in zip(f.grids.factors, f.grids.axes)]
        maxes = [p.abs().flatten(1).amax(1) for p in f.grids.factors]
        groups = [[0, 1, 2, 3]] if kind == "tensorf_cp" else [[p, p + 3] for p in range(3)]
        r = f.rank
        raw_bound = sum((torch.stack([maxes[j][:r] + bounds[j][:r] for j in grp]).prod(0)
                         - torch.stack([maxes[j][:r] for j in grp]).prod(0)).sum()
                        for grp in groups)
        f.upsample(target2)
        s2, _ = f(xyz, t)
        rel = ((s2 - s1).abs() / s1).max().item()
        assert rel <= torch.expm1(raw_bound).item() + 1e-5
        assert rel > 1e-4  # and the grid really changed


def test_state_dict_of_grown_field_loads_into_fresh_field():
    f = _small("hexplane")
    f.upsample((15, 15, 15, 11))
    fresh = _small("hexplane")
    fresh.load_state_dict(f.state_dict())
    xyz, t = _points(100, 3)
    assert fresh.resolution == (15, 15, 15, 11)
    assert torch.equal(fresh(xyz, t)[0], f(xyz, t)[0])


# ---------------------------------------------------------------- Lightning schedules
class _Renderer:
    clip_scale = -1.0


class _ToyModule(pl.LightningModule):
    """Minimal stand-in for the lead's module: optimiser from field.param_groups(lr)."""

    def __init__(self, field: nn.Module):
        super().__init__()
        self.field = field
        self.renderer = _Renderer()
        self.seen: list[tuple[int, float, set[int], tuple[int, ...]]] = []

    def training_step(self, batch, batch_idx):
        xyz, t = _points(256, self.global_step)
        sigma, rgb = self.field(xyz, t)
        opt = self.trainer.optimizers[0]
        ids = {id(p) for grp in opt.param_groups for p in grp["params"]}
        self.seen.append((self.global_step, self.renderer.clip_scale, ids,
                          getattr(self.field, "resolution", ())))
        return (sigma - 1).square().mean() + (rgb - 0.5).square().mean()

    def configure_optimizers(self):
        return torch.optim.Adam(self.field.param_groups(1e-2))

    def train_dataloader(self):
        return torch.utils.data.DataLoader(torch.zeros(64, 1), batch_size=1)


def _fit(module: _ToyModule, steps: int, tmp_path: Path) -> pl.Trainer:
    trainer = pl.Trainer(max_steps=steps, accelerator="cpu", devices=1, logger=False,
                         enable_checkpointing=False, enable_progress_bar=False,
                         enable_model_summary=False, default_root_dir=tmp_path,
                         callbacks=module.field.callbacks())
    trainer.fit(module)
    return trainer


def test_grid_growth_rebuilds_optimiser_in_lightning(tmp_path):
    field = TensoRFCPField(rank=2, resolution_init=(4, 4, 4, 4), resolution_final=(16, 16, 16, 8),
                           n_growth=2, growth_until=0.5)
    module = _ToyModule(field)
    trainer = _fit(module, 8, tmp_path)
    # growth at steps round(k/2 * 0.5 * 8) = 2, 4
    res = [s[3] for s in module.seen]
    assert res == [(4, 4, 4, 4)] * 2 + [(8, 8, 8, 6)] * 2 + [(16, 16, 16, 8)] * 4
    final_ids = {id(p) for p in field.parameters()}
    assert module.seen[-1][2] == final_ids  # the optimiser used at the last step
    opt_ids = {id(p) for g in trainer.optimizers[0].param_groups for p in g["params"]}
    assert opt_ids == final_ids
    # the optimiser state belongs to the new (grown) parameters and they were trained
    state_ids = {id(p) for p in trainer.optimizers[0].state}
    assert state_ids == final_ids
    assert all(trainer.optimizers[0].state[p]["step"] == 4 for p in field.grids.factors)


def test_cylinder_anneal_in_lightning(tmp_path):
    field = _small("ngp", anneal_fraction=0.5)
    module = _ToyModule(field)
    _fit(module, 6, tmp_path)
    assert [s[1] for s in module.seen] == pytest.approx([0, 1 / 3, 2 / 3, 1, 1, 1])
    assert CylinderAnneal(1 / 3).scale(5_000, 30_000) == pytest.approx(0.5)


# ---------------------------------------------------------------- every backbone
@pytest.mark.parametrize("kind", KINDS)
def test_gradients_reach_every_parameter(kind):
    f = _small(kind)
    xyz, t = _points(2000, 4)
    sigma, rgb = f(xyz, t)
    loss = sigma.mean() + rgb.mean()
    reg = f.regularization()
    if reg is not None:
        loss = loss + reg
    loss.backward()
    for name, p in f.named_parameters():
        assert p.grad is not None and p.grad.abs().sum().item() > 0, name
    groups = f.param_groups(1e-2)
    assert sum(len(g["params"]) for g in groups) == len(list(f.parameters()))


def _moving_sphere(xyz: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
    """Density 10 inside a sphere of radius 0.35 moving from x = -0.6 to 0.6, smooth
    edge of width 0.04; smooth colour ramp in x, y and t."""
    c = torch.cat([0.6 * (2 * t - 1), torch.zeros_like(t), torch.full_like(t, 0.2)], -1)
    occ = torch.sigmoid((0.35 - (xyz - c).norm(dim=-1)) / 0.04)
    rgb = torch.stack([0.5 + 0.4 * xyz[:, 0], 0.5 + 0.4 * t[:, 0], 0.5 - 0.3 * xyz[:, 1]], -1)
    return 10 * occ, rgb


# (field, lr, steps, bound on relative density RMSE, bound on colour RMSE); measured
# 0.06 / 0.015, 0.16 / 0.002, 0.15 / 0.002 (a constant predictor scores ~1 / 0.2).
FITS = {
    "ngp": (lambda: NGPField(log2_table_size=14, n_levels=4, base_resolution=4), 1e-2, 300,
            0.12, 0.04),
    "tensorf_cp": (lambda: TensoRFCPField(rank=8, resolution_init=(32, 32, 32, 8),
                                          resolution_final=(32, 32, 32, 8), n_growth=0),
                   2e-2, 300, 0.25, 0.02),
    "hexplane": (lambda: HexPlaneField(rank=4, resolution_init=(32, 32, 32, 8),
                                       resolution_final=(32, 32, 32, 8), n_growth=0),
                 2e-2, 300, 0.25, 0.02),
}


@pytest.mark.parametrize("kind", KINDS)
def test_fits_moving_sphere(kind):
    make, lr, steps, bound_sigma, bound_rgb = FITS[kind]
    f = make()
    opt = torch.optim.Adam(f.param_groups(lr))
    for i in range(steps):
        xyz, t = _points(4096, i)
        sigma, rgb = f(xyz, t)
        ts, tc = _moving_sphere(xyz, t)
        loss = ((sigma - ts) / 10).square().mean() + (rgb - tc).square().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        xyz, t = _points(20000, 10_000)
        sigma, rgb = f(xyz, t)
        ts, tc = _moving_sphere(xyz, t)
    rel = ((sigma - ts).square().mean().sqrt() / ts.square().mean().sqrt()).item()
    err_rgb = (rgb - tc).square().mean().sqrt().item()
    assert rel < bound_sigma and err_rgb < bound_rgb, (rel, err_rgb)


@pytest.mark.parametrize("kind", KINDS)
def test_bf16_autocast_training_step_is_finite(kind):
    f = _small(kind)
    opt = torch.optim.Adam(f.param_groups(1e-2))
    xyz, t = _points(1000, 5)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        sigma, rgb = f(xyz, t)
        loss = (sigma - 1).square().mean() + (rgb - 0.5).square().mean()
        reg = f.regularization()
        if reg is not None:
            loss = loss + reg
    loss.backward()
    assert torch.isfinite(loss).item()
    assert all(torch.isfinite(p.grad).all() for p in f.parameters())
    opt.step()
    assert all(torch.isfinite(p).all() for p in f.parameters())


@pytest.mark.parametrize("kind", KINDS)
def test_edge_coordinates_finite_and_clamped(kind):
    f = _small(kind)
    xyz = torch.tensor([[1.0, 1.0, -1.0], [1.01, 1.2, -1.01], [0.2, 0.1, 0.0],
                        [0.2, 0.1, 0.0], [0.2, 0.1, 0.0], [0.2, 0.1, 0.0]])
    t = torch.tensor([[0.0], [-1e-3], [1.0], [1.001], [0.0], [-1e-3]])
    xyz.requires_grad_(True)
    sigma, rgb = f(xyz, t)
    (sigma.sum() + rgb.sum()).backward()
    assert torch.isfinite(sigma).all() and torch.isfinite(rgb).all()
    # the hash grid does not differentiate w.r.t. its input coordinates (no loss needs it)
    assert (xyz.grad is None) if kind == "ngp" else torch.isfinite(xyz.grad).all()
    assert ((rgb >= 0) & (rgb <= 1)).all() and (sigma >= 0).all()
    assert torch.allclose(sigma[0], sigma[1]) and torch.allclose(sigma[2], sigma[3])
    assert torch.allclose(sigma[4], sigma[5])


# ---------------------------------------------------------------- configs
@pytest.mark.parametrize("name,cls,checks", [
    ("ngp", NGPField, {"log2_table_size": 19, "base_resolution": 8}),
    ("tensorf_cp", TensoRFCPField, {"rank": 8}),
    ("tensorf_cp_paper", TensoRFCPField, {"rank": 8, "resolution_final": [500, 500, 500, 24]}),
    ("tensorf_cp_public", TensoRFCPField, {"rank": 50, "resolution_final": [500, 500, 500, 24]}),
    ("hexplane", HexPlaneField, {"rank": 8}),
    ("hexplane_paper", HexPlaneField, {"rank": 8, "resolution_final": [500, 500, 500, 24]}),
])
def test_model_configs_compose(name, cls, checks):
    from hydra import compose, initialize_config_dir
    from hydra.utils import get_class
    from omegaconf import OmegaConf

    text = (CONF / "model" / f"{name}.yaml").read_text()
    assert text.startswith("# python train.py model=")
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose(overrides=[f"+model={name}"]).model
    assert get_class(cfg._target_) is cls
    assert cfg.optim.lr == (1e-3 if cls is NGPField else 1e-2)
    for key, val in checks.items():
        assert OmegaConf.to_container(cfg)[key] == val
    if "paper" not in name and "public" not in name:  # CPU presets build quickly
        from eventrecon.build import build_field
        f = build_field(cfg)
        s, c = f(*_points(10, 0))
        assert s.shape == (10,) and c.shape == (10, 3)


def test_hexplane_pairs_are_complementary():
    for s, t in PAIRS:
        assert sorted(s + t) == [0, 1, 2, 3] and 3 in t


def test_hexplane_tv_weights_time_and_space_separately():
    """A space-time plane varying only along t costs tv_time; only along space, tv_space."""
    f = HexPlaneField(rank=1, resolution_init=(4, 4, 4, 5), resolution_final=(4, 4, 4, 5),
                      n_growth=0, tv_space=1.0, tv_time=100.0)
    with torch.no_grad():
        for p in f.grids.factors:
            p.fill_(1.0)
        assert float(f.regularization()) == 0.0  # constant planes: no variation
        zt = f.grids.factors[3]  # the (z, t) plane: [2R, R_z, R_t]
        zt.copy_(torch.arange(5.0).expand_as(zt))  # ramp of slope 1 along t only
        assert float(f.regularization()) == pytest.approx(100.0 * 1.0)
        zt.copy_(torch.arange(4.0)[:, None].expand_as(zt))  # ramp along z only
        assert float(f.regularization()) == pytest.approx(1.0 * 1.0)
