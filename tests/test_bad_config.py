"""Bad configuration and scene input: one line naming the key and the expectation.

In-process cases go through :func:`eventrecon.engine.runner.run` with the composed Hydra config
(exactly what ``train.py`` calls) and must raise :class:`InputError` whose message is a
single line matching ``<where>: <key>: expected <expectation>, got <value>``. A few cases
go through ``python train.py`` to check what a user sees: exit status 2 and one
``[ERROR]`` line, no traceback (Hydra's own strict-mode errors exit with 1 and name the
key or list the valid choices). Together with ``test_bad_input.py`` (dataset files).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from integration import TINY, TINY_NERF, tiny_config
from omegaconf.errors import InterpolationResolutionError

from eventrecon.common.errors import InputError
from eventrecon.data.segments import resolve_segments
from eventrecon.engine import build, runner
from eventrecon.engine.segments import segment_steps
from eventrecon.sim.pipeline import ensure_dataset

ROOT = Path(__file__).resolve().parents[1]
FAST = ["trainer.max_steps=4", "evaluate=false"]


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("data")
    ensure_dataset(tiny_config(path).scene, path)
    return path


@pytest.fixture(scope="module")
def nerf_ckpt(data_dir: Path, tmp_path_factory) -> Path:
    """``last.ckpt`` of a 4-step tiny NeRF run."""
    out = tmp_path_factory.mktemp("nerf_run")
    runner.run(tiny_config(data_dir, *FAST), out)
    return out / "seg0" / "checkpoints" / "last.ckpt"


def _raises_one_line(cfg, out: Path, pattern: str) -> InputError:
    with pytest.raises(InputError, match=pattern) as err:
        runner.run(cfg, out)
    assert "\n" not in str(err.value)
    return err.value


# overrides -> the message it must give (regex, searched)
CASES = {
    "misspelt_effect": (["scene.events=[{name:shot_nois,rate_hz:1}]"],
                        r"^scene spheres: events\[0\]\.name: expected one of bandwidth, bayer, "
                        r"hot_pixels, leak, refractory, shot_noise, threshold_mismatch, "
                        r"threshold_noise, timestamp_jitter, got 'shot_nois'$"),
    "unknown_effect_param": (["scene.events=[{name:shot_noise,rate:1}]"],
                             r"events\[0\]\.rate: expected a parameter of shot_noise \(rate_hz"),
    "threshold_zero": (["scene.threshold=0"],
                       r"^scene spheres: threshold: expected a contrast threshold > 0, got 0\.0$"),
    "threshold_negative": (["scene.threshold=-0.2"], r"threshold: expected a contrast threshold"),
    "width_zero": (["scene.width=0"], r"^scene spheres: width: expected an integer > 0, got 0$"),
    "duration_text": (["scene.duration_s=abc"],
                      r"^scene spheres: duration_s: expected a number > 0, got 'abc'$"),
    "negative_shot_noise": (["scene.events=[{name:shot_noise,rate_hz:-1}]"],
                            r"events\[0\]\.rate_hz: expected a rate ≥ 0 Hz per pixel, "
                            r"got -1\.0$"),
    "negative_leak": (["scene.events=[{name:leak,rate_hz:-0.5}]"],
                      r"events\[0\]\.rate_hz: expected a rate ≥ 0 Hz"),
    "negative_refractory": (["scene.events=[{name:refractory,period_s:-0.001}]"],
                            r"events\[0\]\.period_s: expected a period ≥ 0 s, got -0\.001$"),
    "hot_fraction_above_1": (["scene.events=[{name:hot_pixels,fraction:1.5,rate_hz:10}]"],
                             r"events\[0\]\.fraction: expected a fraction, got 1\.5$"),
    "decay_above_1": (["scene.decay=1.5"], r"decay: expected a decay in \(0, 1\], got 1\.5$"),
    "unknown_model_target": (["model._target_=foo.Bar"],
                             r"^config: model\._target_: expected an importable Field class .*"
                             r"got foo\.Bar \(ModuleNotFoundError: No module named 'foo'\)$"),
    "misspelt_model_class": (["model._target_=eventrecon.fields.nerf.NeRFFeld"],
                             r"model\._target_: .*got eventrecon\.fields\.nerf\.NeRFFeld "
                             r"\(AttributeError"),
    "model_not_a_field": (["model._target_=torch.nn.Linear"],
                          r"model\._target_: expected an importable Field class .*"
                          r"got torch\.nn\.Linear$"),
    "unknown_model_argument": (["+model.foo=1"],
                               r"^config: model: expected the arguments of "
                               r"eventrecon\.fields\.nerf\.NeRFField, got .*'foo'$"),
    "model_integer_as_text": (["model.depth=abc"],
                              r"^config: model\.depth: expected an integer, got abc$"),
    "model_integer_as_fraction": (["model.width=2.5"],
                                  r"^config: model\.width: expected an integer, got 2\.5$"),
    "loss_weight_as_text": (["loss.w_rgb=abc"],
                            r"^config: loss\.w_rgb: expected a number, got abc$"),
    "views_too_many": (["data.views=99"],
                       r"^config: data\.views: expected an integer in \[1, 6\] "
                       r"\(views in the dataset\), got 99$"),
    "fps_above_dataset": (["data.fps=50"],
                          r"^config: data\.fps: expected at most the dataset's 5 FPS, got 50"),
    "root_missing": (["data.root=/nonexistent/scene"],
                     r"^/nonexistent/scene: <folder>: expected an existing scene folder"),
    "ckpt_missing": (["ckpt_path=/nonexistent/x.ckpt"],
                     r"^config: ckpt_path: expected an existing checkpoint file or 'last', "
                     r"got /nonexistent/x\.ckpt$"),
}

# keys checked before any data work (eventrecon.engine.run_keys.check_run_keys): before these
# checks a typo gave a traceback from deep inside (Lightning's max_steps and precision
# checks, AdamW's, int('abc'), an IndexError) or surfaced only after the data was read
EARLY = {
    "max_steps_negative": (["trainer.max_steps=-5"],
                           r"^config: trainer\.max_steps: expected an integer number of steps "
                           r">= 1, got -5$"),
    "max_steps_zero": (["trainer.max_steps=0"], r"trainer\.max_steps: .* got 0$"),
    "max_steps_text": (["trainer.max_steps=abc"], r"trainer\.max_steps: .* got abc$"),
    "max_steps_fraction": (["trainer.max_steps=2.5"], r"trainer\.max_steps: .* got 2\.5$"),
    "n_rays_zero": (["trainer.n_rays=0"],
                    r"^config: trainer\.n_rays: expected an integer number of rays >= 1, "
                    r"got 0$"),
    "seed_text": (["seed=abc"], r"^config: seed: expected an integer, got abc$"),
    "segment_text": (["data.segment=abc"],
                     r"^config: data\.segment: expected null \(every segment\) or an "
                     r"integer >= 0, got abc$"),
    "segment_negative": (["data.segment=-1"], r"data\.segment: .* got -1$"),
    "lr_negative": (["model.optim.lr=-1"],
                    r"^config: model\.optim\.lr: expected a finite number > 0, got -1$"),
    "lr_text": (["model.optim.lr=abc"], r"model\.optim\.lr: .* got abc$"),
    "weight_decay_negative": (["model.optim.weight_decay=-0.1"],
                              r"^config: model\.optim\.weight_decay: expected a finite "
                              r"number >= 0, got -0\.1$"),
    "eps_zero": (["+model.optim.eps=0"], r"model\.optim\.eps: expected a finite number > 0"),
    "views_zero": (["data.views=0"],
                   r"^config: data\.views: expected null \(every view\) or an integer >= 1, "
                   r"got 0$"),
    "views_text": (["data.views=abc"], r"data\.views: .* got abc$"),
    "fps_zero": (["data.fps=0"],
                 r"^config: data\.fps: expected null \(every frame\) or a frame rate > 0, "
                 r"got 0$"),
    "fps_text": (["data.fps=abc"], r"data\.fps: .* got abc$"),
    "neg_ratio_text": (["data.neg_ratio=abc"],
                       r"^config: data\.neg_ratio: expected a fraction in \[0, 1\], got abc$"),
    "window_reversed": (["data.window=[500,100]"],
                        r"^config: data\.window: expected null or \[t0, t1\] time units with "
                        r"0 <= t0 < t1 <= 1000, got \[500, 100\]$"),
    "window_text": (["data.window=abc"], r"data\.window: .* got abc$"),
    "window_beyond_the_span": (["data.window=[0,2000]"], r"data\.window: .* got \[0, 2000\]$"),
    "paper_steps_text": (["trainer.paper_steps=abc"],
                         r"^config: trainer\.paper_steps: expected an integer number of "
                         r"steps >= 1, got abc$"),
    "schedule_unknown": (["trainer.schedule=bogus"],
                         r"^config: trainer\.schedule: expected paper or compressed, got bogus$"),
    "lr_end_factor_text": (["trainer.lr_end_factor=abc"], r"trainer\.lr_end_factor: .* got abc$"),
    "betas_power_text": (["model.optim.betas_power=abc"],
                         r"model\.optim\.betas_power: .* got abc$"),
    "model_layers_text": (["model.depth=abc"], r"^config: model\.depth: expected an integer, "
                                               r"got abc$"),
    "loss_weight_text": (["loss.w_rgb=abc"], r"^config: loss\.w_rgb: expected a number, got abc$"),
    "render_samples_text": (["render.n_coarse=abc"],
                            r"^config: render\.n_coarse: expected an integer, got abc$"),
    "precision_unknown": (["trainer.lightning.precision=bogus"],
                          r"^config: trainer\.lightning\.precision: expected auto or one of "
                          r"Lightning's: .*bf16-mixed.*, got bogus$"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_config_value_is_one_line(case: str, data_dir: Path, tmp_path: Path):
    overrides, pattern = CASES[case]
    _raises_one_line(tiny_config(data_dir, *FAST, *overrides), tmp_path, pattern)


@pytest.mark.parametrize("case", sorted(EARLY))
def test_a_bad_run_key_fails_before_any_data_work(case: str, data_dir: Path, tmp_path: Path,
                                                  monkeypatch):
    """The error comes before the run reads (or would simulate) its dataset and before
    it makes its folder: reading the data here fails the test."""
    def no_data(*args, **kwargs):
        raise AssertionError("the dataset was read before the bad key was found")

    monkeypatch.setattr(runner, "load_dataset", no_data)
    overrides, pattern = EARLY[case]
    _raises_one_line(tiny_config(data_dir, *FAST, *overrides), tmp_path / "run", pattern)
    assert not (tmp_path / "run").exists()


def test_whole_numbers_written_as_floats_and_an_empty_window_still_run(data_dir: Path):
    """Hydra parses ``1e3`` as a float: a whole number of steps stays accepted (``int()``
    took it before these checks); ``data.window=[]`` is no window, as before; a null
    precision is Lightning's default."""
    from eventrecon.engine.run_keys import check_run_keys

    cfg = tiny_config(data_dir, "trainer.max_steps=1e3", "data.window=[]",
                      "trainer.lightning.precision=null")
    check_run_keys(cfg)
    assert segment_steps(cfg, 1) == 1000
    with pytest.raises(InputError, match=r"trainer\.max_steps: .* got 1000\.5$"):
        check_run_keys(tiny_config(data_dir, "trainer.max_steps=1000.5"))


def test_a_sweep_records_a_failure_even_when_the_record_reads_the_bad_key(data_dir: Path,
                                                                         tmp_path: Path):
    """A sweep job whose precision is unknown: the failure record (``train.py``'s
    ``_record_failure``) cannot compute the run's precision for its identity, and falls
    back to the identity the config names, instead of a second error in the handler."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("train_entry", ROOT / "train.py")
    train_entry = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(train_entry)
    cfg = tiny_config(data_dir, *FAST, "trainer.lightning.precision=bogus")
    with pytest.raises(InputError) as err:
        runner.run(cfg, tmp_path / "run")
    train_entry._record_failure(cfg, tmp_path, err.value)
    rec = json.loads((tmp_path / "metrics.json").read_text())
    assert rec["status"] == "failed" and rec["model"] == "nerf" and rec["loss"] == "full"
    assert rec["error"].startswith("InputError: config: trainer.lightning.precision: ")


def test_a_schedule_in_the_papers_steps_names_a_bad_step_budget(data_dir: Path):
    """``${paper_steps:N}`` reads ``trainer.max_steps`` when a schedule is compressed: a bad
    budget is named there too (OmegaConf wraps the resolver's error)."""
    cfg = tiny_config(data_dir, "trainer.max_steps=abc", "trainer.schedule=compressed",
                      "model.anneal_steps=${paper_steps:4000}")
    with pytest.raises(InterpolationResolutionError,
                       match=r"trainer\.max_steps: expected an integer number of steps >= 1, "
                             r"got abc"):
        cfg.model.anneal_steps  # noqa: B018 - the resolver runs on access


def test_checkpoint_of_another_backbone(nerf_ckpt: Path, data_dir: Path, tmp_path: Path):
    cfg = tiny_config(data_dir, *FAST, "model=hexplane", f"ckpt_path={nerf_ckpt}", base=TINY)
    err = _raises_one_line(cfg, tmp_path, r"eventrecon\.field_class")
    assert str(err) == (f"{nerf_ckpt}: eventrecon.field_class: expected a checkpoint of "
                        "baselines.hexplane.HexPlaneField (this run's model), got "
                        "eventrecon.fields.nerf.NeRFField")
    assert not (tmp_path / "seg0" / "checkpoints").exists() or not any(
        (tmp_path / "seg0" / "checkpoints").iterdir())  # nothing was trained or saved


def test_module_refuses_foreign_checkpoint_even_without_the_runner(nerf_ckpt: Path,
                                                                   data_dir: Path):
    """The module's own guard (``on_load_checkpoint``) for paths that skip the runner."""
    import torch

    cfg = tiny_config(data_dir, "model=tensorf_cp", base=TINY)
    ds = build.load_dataset(cfg)
    seg = resolve_segments(None)[0]
    mod = build.build_module(cfg, build.scene_properties(cfg, ds), ds.splits["train"], seg)
    state = torch.load(nerf_ckpt, map_location="cpu", weights_only=False)
    with pytest.raises(InputError, match=r"^checkpoint: eventrecon\.field_class: expected a "
                                         r"checkpoint of baselines\.tensorf_cp\.TensoRFCPField"):
        mod.on_load_checkpoint(state)


def test_truncated_checkpoint(nerf_ckpt: Path, data_dir: Path, tmp_path: Path):
    bad = tmp_path / "half.ckpt"
    data = nerf_ckpt.read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    cfg = tiny_config(data_dir, *FAST, f"ckpt_path={bad}")
    _raises_one_line(cfg, tmp_path / "run",
                     rf"^{re.escape(str(bad))}: <file>: expected a checkpoint readable by "
                     r"torch\.load, got ")


def test_checkpoint_that_is_not_a_lightning_checkpoint(data_dir: Path, tmp_path: Path):
    import torch

    bad = tmp_path / "weights.ckpt"
    torch.save({"weights": torch.zeros(3)}, bad)
    cfg = tiny_config(data_dir, *FAST, f"ckpt_path={bad}")
    _raises_one_line(cfg, tmp_path / "run",
                     rf"^{re.escape(str(bad))}: state_dict: expected a Lightning checkpoint, "
                     r"got missing$")


# ------------------------------------------------------------------ through `python train.py`
def _train_py(*overrides: str, data_dir: Path, run_dir: Path,
              base: list[str] = TINY + TINY_NERF) -> tuple[int, str]:
    cmd = [sys.executable, str(ROOT / "train.py"), *base, *FAST,
           f"data_dir={data_dir}", f"hydra.run.dir={run_dir}", *overrides]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "EVENTRECON_OFFLINE": "1"}
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    return proc.returncode, proc.stdout + proc.stderr


@pytest.mark.parametrize("override, line", [
    ("scene.threshold=0", "scene spheres: threshold: expected a contrast threshold > 0, got 0.0"),
    ("scene.events=[{name:refractory,period_s:-1}]",
     "scene spheres: events[0].period_s: expected a period ≥ 0 s, got -1.0"),
    ("trainer.max_steps=-5",
     "config: trainer.max_steps: expected an integer number of steps >= 1, got -5"),
])
def test_train_py_prints_one_error_line_and_exits_2(override: str, line: str, data_dir: Path,
                                                   tmp_path: Path):
    rc, out = _train_py(override, data_dir=data_dir, run_dir=tmp_path)
    assert rc == 2, out[-2000:]
    assert "Traceback" not in out
    errors = [ln for ln in out.splitlines() if "[ERROR]" in ln]
    assert len(errors) == 1 and errors[0].endswith(line)


def test_train_py_foreign_checkpoint(nerf_ckpt: Path, data_dir: Path, tmp_path: Path):
    rc, out = _train_py("model=hexplane", f"ckpt_path={nerf_ckpt}", data_dir=data_dir,
                        run_dir=tmp_path, base=TINY)
    assert rc == 2, out[-2000:]
    assert "Traceback" not in out
    errors = [ln for ln in out.splitlines() if "[ERROR]" in ln]
    assert len(errors) == 1
    assert errors[0].endswith(f"{nerf_ckpt}: eventrecon.field_class: expected a checkpoint of "
                              "baselines.hexplane.HexPlaneField (this run's model), got "
                              "eventrecon.fields.nerf.NeRFField")


@pytest.mark.parametrize("override, must_contain", [
    ("trainer.max_stepz=3", ["Could not override 'trainer.max_stepz'",
                             "Key 'max_stepz' is not in struct"]),
    ("loss=no_evnt", ["Could not find 'loss/no_evnt'", "Available options in 'loss':",
                      "\tno_event\n", "\tonly_rgb\n"]),
    ("model=hexplan", ["Could not find 'model/hexplan'", "\thexplane\n"]),
    # a list addressed by a name: OmegaConf's ValueError used to escape Hydra as a traceback
    ("scene.objects.0.motion.type=spin",
     ["command line: scene.objects.0.motion.type: expected scene.objects.0.motion's items "
      "addressed by their index (scene.objects.0.motion is a list), e.g. "
      "scene.objects.0.motion.0.type, got scene.objects.0.motion.type=spin ("]),
])
def test_hydra_strict_mode_names_the_key_or_lists_choices(override: str, must_contain: list,
                                                           tmp_path: Path):
    rc, out = _train_py(override, data_dir=tmp_path / "unused", run_dir=tmp_path)
    assert rc == 1
    assert "Traceback" not in out
    for text in must_contain:
        assert text in out
    assert not (tmp_path / "unused").exists()  # failed before any simulation
