"""Train Dynamic EventNeRF (or any backbone of the zoo) on a scene, then evaluate it.

    python train.py                                  # spheres, NeRF MLP, full loss, CPU preset
    python train.py model=hexplane loss=no_event     # a backbone and an ablation row
    python train.py -m experiment=table3 scale=cpu   # a sweep that regenerates Tab. 3
    python train.py data.root=/path/to/scene         # a dataset in the published layout

The run reads top to bottom in :func:`eventrecon.engine.runner.run`: data → field → module →
callbacks → logger → trainer → fit → evaluate. Held-out PSNR / SSIM / LPIPS are printed
at the end and saved to ``metrics.json`` in the run folder.

Exit status: 0 done; 2 bad input (one line naming the file or config key and the
expectation); 3 stopped by the non-finite-loss guard (one line, checkpoint kept). In a
sweep (``-m``) a failing job writes ``metrics.json`` with ``status: failed`` instead.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

import eventrecon  # noqa: F401 - registers the config resolvers (${paper_steps:...})

log = logging.getLogger("eventrecon.train")


def _pick_trainer_preset(argv: list[str]) -> list[str]:
    """``trainer=gpu`` when a GPU is present and the user chose no trainer preset."""
    if any(a.startswith(("trainer=", "+trainer=", "experiment=", "scale=")) for a in argv):
        return argv
    import torch

    return argv + ["trainer=gpu"] if torch.cuda.is_available() else argv


@hydra.main(config_path="conf", config_name="config", version_base="1.3")
def main(cfg: DictConfig) -> float | None:
    from eventrecon.common.errors import InputError
    from eventrecon.common.malloc import retain_freed_memory
    from eventrecon.engine.module import NonFiniteLossError
    from eventrecon.engine.runner import run
    from eventrecon.results.records import finished_metrics

    _one_log_stream()
    retain_freed_memory()  # a step's freed activations stay in the heap (eventrecon.common.malloc)

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    multirun = HydraConfig.get().mode == RunMode.MULTIRUN
    _share_cores_between_parallel_jobs()
    previous = (finished_metrics(out_dir / "metrics.json", cfg.trainer.max_steps, cfg.evaluate)
                if multirun and cfg.data.segment is None else None)
    if previous is not None:
        log.info("%s: finished before, skipped", out_dir)
        return previous.get("psnr")
    try:
        metrics = run(cfg, out_dir)
    except InputError as e:
        if multirun:
            return _record_failure(cfg, out_dir, e)
        log.error("%s", e)
        sys.exit(2)
    except NonFiniteLossError as e:  # the guard stopped a diverging run (checkpoint kept)
        if multirun:
            return _record_failure(cfg, out_dir, e)
        log.error("%s", e)
        sys.exit(3)
    except Exception as e:  # noqa: BLE001 - a failed sweep job must not stop the sweep
        if multirun:
            log.exception("job failed")
            return _record_failure(cfg, out_dir, e)
        raise
    if metrics.get("rank"):  # a DDP worker: rank 0 evaluates and reports
        return None
    if metrics["status"] == "partial":
        log.info("segment %s trained; the run is evaluated once segments %s are trained too",
                 cfg.data.segment, metrics["missing_segments"])
        return None
    from eventrecon.evaluation.summary import format_summary

    emit = log.warning if metrics["status"] == "collapsed" else log.info
    emit("%s", format_summary(metrics, out_dir))
    return metrics.get("psnr")


#: Lightning's lines that say nothing about this run (hardware it does not use, an
#: advertisement, the end of fit, which the runner reports itself).
_CHATTER = ("GPU available", "TPU available", "HPU available", "IPU available", "litlogger",
            "LitLogger", "`Trainer.fit` stopped", "Seed set to")


class _QuietLightning(logging.Filter):
    """Drops :data:`_CHATTER` lines; on a GPU run the GPU line stays (it says which)."""

    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.getMessage()
        if msg.startswith("GPU available: True"):
            return True
        return not any(c in msg for c in _CHATTER)


def _one_log_stream() -> None:
    """Lightning's messages once, through Hydra's handlers (console and the run's log file),
    without its chatter (:data:`_CHATTER`).

    ``import lightning`` adds its own console handler to the ``lightning`` logger, which
    also propagates to the root logger that Hydra configured: every message came twice.
    Lightning's internal ``LeafSpec`` deprecation warning is not the user's to act on, nor
    is its hint about DataLoader workers (the loader here only counts steps).
    """
    import warnings

    logging.getLogger("lightning").handlers.clear()
    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero",
                 "lightning.pytorch.accelerators.cuda"):
        logging.getLogger(name).addFilter(_QuietLightning())
    warnings.filterwarnings("ignore", message=r".*does not have many workers.*")
    warnings.filterwarnings("ignore", message=r".*number of training batches.*")
    warnings.filterwarnings("ignore", message=r".*LeafSpec.*", category=DeprecationWarning)
    warnings.filterwarnings("ignore", message=r".*LeafSpec.*", category=FutureWarning)


def _share_cores_between_parallel_jobs() -> None:
    """Under ``hydra/launcher=joblib`` give each job ``cores // n_jobs`` torch threads.

    Jobs running side by side each with torch's default (all cores) oversubscribe the
    machine; with OpenMP's busy waiting that was measured here ~10x slower per step.
    """
    import os

    import torch

    launcher = HydraConfig.get().launcher
    if "joblib" not in str(launcher.get("_target_", "")):
        return
    cores = os.cpu_count() or 1
    n_jobs = int(launcher.get("n_jobs", -1) or -1)
    n_jobs = cores + 1 + n_jobs if n_jobs < 0 else n_jobs  # joblib: -1 = every core
    torch.set_num_threads(max(1, cores // max(1, n_jobs)))


def _record_failure(cfg: DictConfig, out_dir: Path, err: BaseException) -> None:
    """Write ``metrics.json`` with ``status: failed`` so the report shows the failure."""
    from eventrecon.engine.build import planned_run_info
    from eventrecon.results.records import METHOD_VERSION, write_metrics

    try:
        info = planned_run_info(cfg)
    except Exception:  # noqa: BLE001 - the bad value may be one the record itself reads
        info = {"scene": (cfg.get("scene") or {}).get("name") or cfg.data.get("root"),
                "model": cfg.model.get("name"), "loss": cfg.loss.get("name"),
                "views": cfg.data.get("views"), "fps": cfg.data.get("fps"),
                "experiment": cfg.get("sweep_name"), "tag": cfg.get("tag"),
                "seed": cfg.get("seed"), "method_version": METHOD_VERSION}
    write_metrics(out_dir, {**info, "status": "failed", "error": f"{type(err).__name__}: {err}"})
    log.error("job failed: %s", err)
    return None


if __name__ == "__main__":
    from eventrecon.config.overrides import report_bad_overrides

    sys.argv = [sys.argv[0], *_pick_trainer_preset(sys.argv[1:])]
    report_bad_overrides()
    main()
