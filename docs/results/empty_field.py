"""The empty field's score for sweep runs made before ``psnr_background`` existed.

    python docs/results/empty_field.py multirun/table3/*/ multirun/table4/*/

For each run folder: PSNR of the background alone (what a field with zero density
renders) against the ground truth, on the frames and views the run itself was scored on,
beside the run's PSNR. It calls the same ``evaluate_heldout`` that writes
``psnr_background`` into ``metrics.json`` of every newer run.
"""

from __future__ import annotations

import json
import logging
import sys
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from eventrecon import runner
from eventrecon.data.batcher import background_linear
from eventrecon.evaluate import evaluate_heldout

log = logging.getLogger("empty_field")


def main(folders: list[str]) -> None:
    cache: dict[tuple, float] = {}
    for folder in map(Path, folders):
        if not (folder / "metrics.json").exists():
            continue
        cfg = OmegaConf.load(folder / ".hydra" / "config.yaml")
        ds = runner.load_dataset(cfg)
        held = runner.heldout_split(ds)
        frames = list(range(0, len(held.frame_times), int(cfg.data.eval_every_frames)))
        views = list(range(held.n_views))
        key = (str(ds.root), tuple(frames), tuple(views))
        if key not in cache:
            bg = background_linear(held).numpy()[views]
            cache[key] = evaluate_heldout(np.stack([bg] * len(frames)), held, views, frames,
                                          lpips=False)["psnr"]
        psnr = json.loads((folder / "metrics.json").read_text())["psnr"]
        log.info("%s: empty %.3f dB, run %.3f dB, gain %+.3f dB",
                 folder.name, cache[key], psnr, psnr - cache[key])


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    main(sys.argv[1:])
