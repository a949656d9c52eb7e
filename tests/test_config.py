"""Config composition: presets switch exactly their terms; bad keys fail clearly."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

CONF = str(Path(__file__).resolve().parents[1] / "conf")
TERMS = ("w_event", "w_acc", "w_rgb", "lam_sparsity")
#: keys an ablation row changes in the group that uses them
SWITCHES = (("render", "clipping"), ("data", "decay"), ("data", "segments"))

# preset -> the keys it changes with respect to `full`, and their values
EXPECTED = {
    "full": {},
    "no_event": {"w_event": 0.0},
    "no_acc": {"w_acc": 0.0},
    "no_rgb": {"w_rgb": 0.0},
    "no_sparsity": {"lam_sparsity": 0.0},
    "only_event": {"w_acc": 0.0, "w_rgb": 0.0},
    "only_acc": {"w_event": 0.0, "w_rgb": 0.0},
    "only_rgb": {"w_event": 0.0, "w_acc": 0.0},
    "no_clipping": {"render.clipping": False},
    "no_decay": {"data.decay": 1.0},
    "no_multiseg": {"data.segments": [[0, 1000]]},
}


def _compose(*overrides: str):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def test_defaults():
    cfg = _compose()
    assert cfg.loss.name == "full"
    loss = cfg.loss
    assert (loss.w_event, loss.w_acc, loss.w_rgb, loss.lam_sparsity) == (1.0, 1.0, 0.01, 0.01)
    assert cfg.data.neg_ratio == 0.9
    # schedules are in the paper's steps at every scale by default
    schedule = (cfg.trainer.schedule, cfg.model.anneal_steps, cfg.loss.sparsity_ramp)
    assert schedule == ("paper", 4000, 30000)
    # trainer=cpu sizes the NeRF MLP for 2 cores (conf/sizing/cpu_nerf.yaml: 4x64, lr 1e-3);
    # the paper's size and lr at trainer=paper (test_paper_trainer_preset_has_paper_values)
    assert (cfg.model.depth, cfg.model.width, cfg.model.optim.lr) == (4, 64, 1e-3)
    # ... and Adam's betas to the power 10 there (method version 4); the authors' elsewhere
    assert cfg.model.optim.betas_power == 10 and list(cfg.model.optim.betas) == [0.9, 0.999]
    assert _compose("trainer=paper").model.optim.betas_power == 1.0
    # NGP: the authors' AdamW at the paper's size, instant-NGP's optimiser at the CPU size
    ngp, paper = (_compose("model=ngp", *t).model.optim for t in ((), ("trainer=paper",)))
    assert (ngp.lr, list(ngp.betas), ngp.eps, ngp.betas_power) == (1e-2, [0.9, 0.99], 1e-15, 1.0)
    assert (paper.lr, list(paper.betas), paper.eps) == (1e-3, [0.9, 0.999], 1e-8)


def test_compressed_schedules_are_a_named_option_and_the_ramp_is_never_compressed():
    cpu = _compose("scale=cpu")
    assert (cpu.trainer.max_steps, cpu.trainer.schedule) == (1000, "compressed")
    assert cpu.model.anneal_steps == round(4000 * 1000 / 150000)  # 27
    assert _compose("scale=cpu", "model=ngp").model.anneal_steps == 67  # 1e4 of 150k
    assert _compose("scale=cpu", "model=tensorf_cp").model.growth_steps == 67
    assert cpu.loss.sparsity_ramp == 30000
    from eventrecon.engine.losses import sparsity_weight
    assert sparsity_weight(1000, cpu.loss.lam_sparsity, cpu.loss.sparsity_ramp) == (
        pytest.approx(1e-2 * (1 - math.exp(-1000 / 30000)), rel=1e-12))
    from eventrecon.common.errors import InputError
    from eventrecon.engine.build import build_field

    with pytest.raises(InputError, match="trainer.schedule: expected paper or compressed, "
                                         "got squeezed$"):
        build_field(_compose("trainer.schedule=squeezed").model)


def test_sizing_applies_only_to_its_trainer_and_model():
    ngp = _compose("model=ngp")
    assert ngp.model.optim.lr == 1e-2 and "depth" not in ngp.model  # conf/sizing/cpu_ngp.yaml
    assert ngp.model.log2_table_size == 17  # conf/sizing/cpu_ngp.yaml
    assert _compose("model=ngp", "trainer=paper").model.log2_table_size == 19
    override = _compose("model.depth=8", "model.width=256")  # the command line still wins
    assert (override.model.depth, override.model.width) == (8, 256)


@pytest.mark.parametrize("preset", sorted(EXPECTED))
def test_loss_preset_switches_exactly_its_terms(preset: str):
    full = OmegaConf.to_container(_compose(), resolve=True)
    mine = OmegaConf.to_container(_compose(f"loss={preset}"), resolve=True)
    changed = {k: mine["loss"][k] for k in TERMS if mine["loss"][k] != full["loss"][k]}
    changed |= {f"{g}.{k}": mine[g][k] for g, k in SWITCHES if mine[g][k] != full[g][k]}
    assert changed == EXPECTED[preset]
    assert mine["loss"]["name"] == preset
    assert set(mine["loss"]) == set(full["loss"])  # the loss group holds only loss weights


def test_every_loss_file_is_tested():
    files = {p.stem for p in (Path(CONF) / "loss").glob("*.yaml")}
    assert files == set(EXPECTED)


def test_paper_trainer_preset_has_paper_values():
    cfg = _compose("trainer=paper")
    assert (cfg.trainer.n_rays, cfg.render.n_coarse, cfg.render.n_fine) == (1024, 64, 128)
    assert cfg.trainer.max_steps == 150000
    # every sample in the cylinder reaches the network, as in the authors' code (the
    # occupancy grid is an opt-in acceleration at the paper's settings)
    assert cfg.render.skip == "none" and _compose("scale=paper").render.skip == "none"
    assert _compose().render.skip == "grid"
    # the paper's network, optimiser and schedules (method.md)
    m = cfg.model
    assert (m.depth, m.width, m.skip, m.pos_bands, m.time_bands, m.colour_width) == (
        8, 256, 4, 14, 7, 128)
    assert (m.optim.lr, m.optim.weight_decay) == (1e-4, 0.1)
    assert m.anneal_steps == 4000 and cfg.loss.sparsity_ramp == 30000
    assert (cfg.loss.lam_sparsity, cfg.loss.w_rgb) == (1e-2, 0.01)


def test_unknown_option_lists_valid_choices():
    with pytest.raises(ConfigCompositionException, match="Available options"):
        _compose("loss=no_evnt")


def test_unknown_key_is_rejected():
    with pytest.raises(ConfigCompositionException, match="trainer.max_stepz"):
        _compose("trainer.max_stepz=3")


def test_every_yaml_starts_with_usage_comment():
    for p in Path(CONF).rglob("*.yaml"):
        first = p.read_text().splitlines()[0]
        if first.startswith("# @package"):
            first = p.read_text().splitlines()[1]
        assert first.startswith("# "), p


@pytest.mark.parametrize("launcher,target", [
    ("joblib", "hydra_plugins.hydra_joblib_launcher.joblib_launcher.JoblibLauncher"),
    ("submitit_slurm", "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"),
    ("slurm_gpu", "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"),
])
def test_sweep_launchers_compose(launcher: str, target: str):
    """The existing engines for scale: joblib locally, SLURM through submitit."""
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(config_name="config", return_hydra_config=True,
                      overrides=["experiment=table6", "scale=smoke", f"hydra/launcher={launcher}"])
    assert cfg.hydra.launcher._target_ == target
    if launcher == "slurm_gpu":
        assert (cfg.hydra.launcher.gpus_per_node, cfg.hydra.launcher.timeout_min) == (1, 1440)


def test_ddp_trainer_preset():
    cfg = _compose("trainer=ddp")
    assert cfg.trainer.lightning.strategy == "ddp" and cfg.trainer.lightning.devices == -1
    assert (cfg.trainer.n_rays, cfg.render.n_coarse, cfg.render.n_fine) == (1024, 64, 128)


def test_davis_size_is_one_override_for_every_scene():
    for scene in ("spheres", "blocks", "rig_lowlight", "static"):
        cfg = _compose(f"scene={scene}", "resolution=davis346")
        assert (cfg.scene.width, cfg.scene.height) == (346, 260), scene
        assert cfg.scene.name == scene


@pytest.mark.parametrize("scene, noise", [
    ("rig_noisy", {"name": "shot_noise", "rate_hz": 5.0}),
    ("rig_drift", {"name": "shot_noise", "rate_hz": 20.0, "on_fraction": 0.8}),
])
def test_the_decay_scenes_are_rig_lowlight_with_only_the_shot_noise_changed(scene, noise):
    # the noisier rig scenes restate rig_lowlight's event effects (Hydra replaces lists): they
    # must stay identical except the shot noise, or the decay comparison would test two changes
    low = OmegaConf.to_container(_compose("scene=rig_lowlight").scene)
    noisy = OmegaConf.to_container(_compose(f"scene={scene}").scene)
    assert [e for e in low["events"] if e["name"] == "shot_noise"] == [
        {"name": "shot_noise", "rate_hz": 0.5}]
    assert [e for e in noisy["events"] if e["name"] == "shot_noise"] == [noise]
    assert noisy.pop("name") == scene
    low.pop("name")
    for s in (low, noisy):
        s["events"] = [e for e in s["events"] if e["name"] != "shot_noise"]
    assert noisy == low
