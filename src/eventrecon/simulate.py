"""Simulate a scene into the published dataset layout.

    python -m eventrecon.simulate scene=blocks
    python -m eventrecon.simulate scene=spheres scene.width=346 scene.height=260
    python -m eventrecon.simulate scene=rig_lowlight data_dir=/tmp/data force=true

The dataset lands in ``<data_dir>/<scene name>-<config hash>/`` (see
:func:`eventrecon.sim.pipeline.ensure_dataset`); an existing one is reused unless
``force=true``. Bad scene values end with one line naming the field, no traceback.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from eventrecon.common.errors import InputError
from eventrecon.config.overrides import report_bad_overrides
from eventrecon.sim.pipeline import ensure_dataset

log = logging.getLogger("eventrecon.simulate")


def _config_dir() -> str:
    """``conf/`` of the repository: beside the package's source tree, else the cwd's."""
    here = Path(__file__).resolve().parents[2] / "conf"
    return str(here if here.is_dir() else Path.cwd() / "conf")


def run(cfg: DictConfig) -> Path:
    """Simulate ``cfg.scene`` under ``cfg.data_dir`` (re-simulate with ``cfg.force``; the
    existing dataset is replaced only once the new one is complete)."""
    path = ensure_dataset(cfg.scene, cfg.data_dir, force=bool(cfg.get("force", False)))
    log.info("dataset: %s", path)
    return path


@hydra.main(config_path=_config_dir(), config_name="simulate", version_base="1.3")
def main(cfg: DictConfig) -> None:
    try:
        run(cfg)
    except InputError as e:
        log.error("%s", e)
        sys.exit(2)


if __name__ == "__main__":
    from eventrecon.common.malloc import retain_freed_memory

    retain_freed_memory()
    report_bad_overrides()
    main()
