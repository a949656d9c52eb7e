"""Helpers for tests that train: compose a tiny config and a shared simulated dataset."""

from __future__ import annotations

from pathlib import Path

from hydra import compose, initialize_config_dir
from omegaconf import DictConfig

CONF = str(Path(__file__).resolve().parents[1] / "conf")

#: A tiny scene and run: seconds on 2 cores.
TINY = [
    "scene.width=32", "scene.height=24", "logger=none",
    "trainer.n_rays=96", "render.n_coarse=12", "render.n_fine=12",
    "trainer.eval_every=0", "trainer.curve_every=0", "trainer.checkpoint_every=10",
    "render.chunk=4096", "data.eval_every_frames=5",
]
#: A tiny NeRF MLP (the default model) for the same runs.
TINY_NERF = [
    "model.depth=3", "model.width=48", "model.pos_bands=6", "model.time_bands=4",
    "model.anneal_steps=0", "model.optim.lr=5e-3", "model.optim.weight_decay=0.0",
]


def tiny_config(data_dir: Path, *overrides: str, base: list[str] | None = None) -> DictConfig:
    """Compose ``conf/config.yaml`` with :data:`TINY` and ``overrides`` (later wins)."""
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        return compose(config_name="config",
                       overrides=[*(TINY + TINY_NERF if base is None else base),
                                  f"data_dir={data_dir}",
                                  *overrides])
