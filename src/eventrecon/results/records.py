"""Run records: the one owner of ``metrics.json``, ``curve.csv`` and ``seg<k>/done.json``.

A run folder holds

- ``metrics.json``: the run's identity (:data:`REQUIRED_KEYS`: ``scene, model, loss,
  views, fps, status``; optionally ``experiment``, ``tag``, ``seed``, ``method_version``
  (:data:`METHOD_VERSION`; a record without one is version 1), and what it changed
  from the paper's method: ``schedule``, ``skip``, ``sizing``) and, once
  evaluated, ``psnr, ssim, lpips`` (LPIPS-Alex), ``lpips_vgg`` (each may be null with a
  ``<key>_note``),
  ``psnr_background`` (the empty field's score on the same frames), ``wall_s``,
  ``steps``, ``sec_per_it``, ``peak_mem_mb``, ``total_s``, ``machine``
  (:mod:`eventrecon.results.machine`). ``status`` is one of
  :data:`STATUSES`: ``ok``; ``collapsed`` (the field renders the empty scene,
  :mod:`eventrecon.engine.collapse`, with ``collapse_reason``); ``failed`` (with ``error``);
  ``partial`` (some segments of a ``data.segment=K`` sweep are still to train; never
  written, only returned);
- ``curve.csv``: :data:`CURVE_HEADER` rows, ``kind`` = ``cheap`` (a subsampled held-out
  image) or ``full``; an empty cell is a missing value. Written per segment
  (``seg<k>/curve.csv``, the segment's own steps and training seconds) and, once the
  run is done, for the whole run (:func:`stitch_curves`);
- ``seg<k>/done.json``: a trained segment — ``max_steps`` (its budget), ``steps``,
  ``wall_s``, ``nonfinite_steps``, ``opacity_log`` (``[step, mean opacity]`` pairs),
  ``method_version``.

A finished run (or segment) made with another :data:`METHOD_VERSION` is not finished for
a sweep: it trains again, and the report reads only the newest version of each job
(:func:`eventrecon.report.runs.current_runs`). A version that changed only some runs
(:data:`VERSION_SCOPE`) leaves the others' records current (:func:`record_version`).

Readers (:mod:`eventrecon.report.runs`) and writers (the runner, the held-out monitor)
both use the names and functions here, so the format has one definition.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

from eventrecon.common.errors import InputError
from eventrecon.common.files import atomic_write_bytes, atomic_write_json
from eventrecon.config.naming import dataset_name, name_from_meta
from eventrecon.config.precision import image_dtype, run_precision

__all__ = ["METHOD_VERSION", "METHOD_VERSIONS", "VERSION_SCOPE", "VERSION_KEYS", "made_version",
           "record_version", "stale_reason", "METRICS_FILE", "CURVE_FILE", "DONE_FILE",
           "CURVE_HEADER", "REQUIRED_KEYS", "STATUSES", "run_info", "sizing_choice",
           "write_metrics", "read_metrics", "finished_metrics", "write_done", "read_done",
           "CurveLog", "read_curve_rows", "write_curve", "stitch_curves"]

#: Version of the training method: bumped by every change that alters what a run trains
#: (sampling, rendering, losses, optimiser) and so makes earlier records stale.
METHOD_VERSION = 5
#: What each version changed (the report's footnote for tables that mix versions).
METHOD_VERSIONS: dict[int, str] = {
    1: "each of a ray's three renders (t0, t1, t_ref) drew its own coarse samples",
    2: "a ray's three renders share their coarse samples, as in the authors' code; the "
       "occupancy grid re-asks a quarter of its occupied cells per update",
    3: "the authors' sample placement and quadrature (evenly spaced coarse points jittered "
       "in half-wide end cells, forward-difference steps, the fine histogram over the coarse "
       "midpoints), a reference frame drawn per view, and per-view pixel draws without "
       "replacement with the authors' int() count of event rays",
    4: "the CPU NeRF (sizing cpu_nerf: 10x the authors' lr) trains with Adam's betas to "
       "the power 10 (model.optim.betas_power: the moments forget over the authors' path "
       "length); NGP at the paper's size takes the authors' AdamW betas and eps (0.9, "
       "0.999; 1e-8), not instant-NGP's, which its CPU sizing keeps",
    5: "HexPlane at its CPU size (sizing cpu_hexplane) has 48 vertices per axis, not 128: "
       "the better grid at the CPU budgets (conf/sizing/cpu_hexplane.yaml)",
}


def _v4_changed(sizing: str) -> bool:
    """Version 4 changed the CPU NeRF (betas^10) and NGP at every size but the CPU's (the
    authors' betas and eps; the CPU sizing names instant-NGP's, as before)."""
    return sizing == "cpu_nerf" or (sizing.endswith("_ngp") and sizing != "cpu_ngp")


def _v5_changed(sizing: str) -> bool:
    """Version 5 changed HexPlane's CPU size only (48 vertices per axis, not 128)."""
    return sizing == "cpu_hexplane"


#: Versions that changed only some runs: whether each one changed the runs of a sizing
#: choice (``<trainer>_<model>``, e.g. ``cpu_nerf``; Hydra records it even where no such
#: file exists). A record of any other run made before it stands for that version too (it
#: trains the same).
VERSION_SCOPE: dict[int, Callable[[str], bool]] = {4: _v4_changed, 5: _v5_changed}
#: Job keys (of a record's identity, :data:`eventrecon.report.runs.JOB_KEYS`) whose default
#: a version changed: a run of that version supersedes an older run of the same job that
#: differs from it only in those keys (it trained with the old default), as a re-run does.
VERSION_KEYS: dict[int, tuple[str, ...]] = {4: ("betas_power",)}

METRICS_FILE = "metrics.json"
CURVE_FILE = "curve.csv"
DONE_FILE = "done.json"
CURVE_HEADER: tuple[str, ...] = ("wall_s", "step", "psnr", "ssim", "lpips", "kind")
REQUIRED_KEYS: tuple[str, ...] = ("scene", "model", "loss", "views", "fps", "status")
#: Statuses a ``metrics.json`` may carry.
STATUSES: tuple[str, ...] = ("ok", "collapsed", "failed")
#: Statuses of a run that trained and was evaluated (a sweep does not run it again).
FINISHED: tuple[str, ...] = ("ok", "collapsed")
#: Keys written as ``null`` when a record does not have them (the report reads them).
OPTIONAL_KEYS: tuple[str, ...] = ("psnr", "ssim", "lpips", "lpips_note", "lpips_vgg",
                                  "lpips_vgg_note", "wall_s", "steps", "sec_per_it",
                                  "peak_mem_mb", "error")


# ---------------------------------------------------------------------------- metrics.json
def run_info(cfg: Any, meta: Mapping[str, Any], views: int | None = None,
             fps: float | None = None, data_id: str | None = None) -> dict[str, Any]:
    """What identifies a run in the reports: scene, model, loss, views, fps, experiment,
    tag and seed (``cfg`` is the run's composed config, ``meta`` the dataset's). The scene
    is the dataset's own name for a ``data.root`` run (:mod:`eventrecon.config.naming`);
    ``data_id`` the dataset folder's name (a simulated scene's carries the hash of its
    spec, so a changed scene makes earlier records of it stale: :func:`stale_reason`)."""
    name = (dataset_name(cfg.data.root, None) if cfg.data.get("root")
            else name_from_meta(meta) or cfg.scene.get("name", "custom"))
    precision = run_precision(cfg)
    return {"scene": name,
            "model": cfg.model.get("name") or str(cfg.model.get("_target_")),
            "loss": cfg.loss.get("name", "full"),
            "views": views if views is not None else cfg.data.views,
            "fps": fps if fps is not None else (cfg.data.fps or meta.get("rgb_fps")),
            "experiment": cfg.get("sweep_name"), "tag": cfg.get("tag"), "seed": cfg.get("seed"),
            # what the run changed from the paper's method (the tables footnote it)
            "schedule": cfg.trainer.get("schedule"), "skip": cfg.render.get("skip"),
            "sizing": sizing_choice(), "method_version": METHOD_VERSION,
            "lr_end_factor": float(cfg.trainer.get("lr_end_factor", 1.0)),
            "lr_warmup": int(cfg.trainer.get("lr_warmup", 0)),
            # where the decay starts; 0 when the lr does not decay (then it changes nothing)
            "lr_decay_start": float(cfg.trainer.get("lr_decay_start", 0.0))
            if float(cfg.trainer.get("lr_end_factor", 1.0)) != 1.0 else 0.0,
            "betas_power": float((cfg.model.get("optim", {}) or {}).get("betas_power", 1.0)),
            "precision": str(precision),
            # held-out images rendered under that precision's autocast (records without the
            # key rendered them in fp32)
            "image_autocast": image_dtype(cfg.render, precision, _device_type(cfg)) is not None,
            "data_id": data_id}


def _device_type(cfg: Any) -> str | None:
    """``"cpu"`` for a run its trainer keeps on the CPU, else ``None`` (a GPU, or ``auto``)."""
    lightning = cfg.trainer.get("lightning") or {}
    return "cpu" if str(lightning.get("accelerator", "cpu")) == "cpu" else None


def sizing_choice() -> str | None:
    """The ``sizing`` config picked for this run (``cpu_nerf`` ...), inside a Hydra app."""
    try:
        from hydra.core.hydra_config import HydraConfig

        return HydraConfig.get().runtime.choices.get("sizing")
    except Exception:  # noqa: BLE001 - outside a Hydra app: unknown
        return None


def write_metrics(folder: str | Path, metrics: Mapping[str, Any]) -> Path:
    """Write ``folder/metrics.json`` atomically; keys of the contract it lacks are null."""
    path = Path(folder) / METRICS_FILE
    missing = [k for k in REQUIRED_KEYS if k not in metrics]
    if missing:
        raise InputError(path, ",".join(missing), "present (metrics.json contract)", "missing")
    atomic_write_json(path, {k: metrics.get(k) for k in OPTIONAL_KEYS} | dict(metrics))
    return path


def read_metrics(path: str | Path) -> dict[str, Any]:
    """A validated ``metrics.json`` (:class:`InputError` naming the file and key otherwise)."""
    path = Path(path)
    try:
        rec = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(path, "(file)", "a readable JSON object", type(exc).__name__) from exc
    if not isinstance(rec, dict):
        raise InputError(path, "(top level)", "a JSON object", type(rec).__name__)
    for key in REQUIRED_KEYS:
        if key not in rec:
            raise InputError(path, key, "present (metrics.json contract)", "missing")
    if rec["status"] not in STATUSES:
        raise InputError(path, "status", " or ".join(map(repr, STATUSES)), repr(rec["status"]))
    return rec


def finished_metrics(path: str | Path, max_steps: int, evaluate: bool,
                     steps: int | None = None, data_id: str | None = None) -> dict | None:
    """``metrics.json`` of the same finished run (status ok or collapsed, the same
    ``max_steps`` and, when given, the same ``steps``; made by this method on the dataset
    ``data_id``, :func:`stale_reason`; scored if ``evaluate``), else ``None``."""
    path = Path(path)
    if not path.exists():
        return None
    done = json.loads(path.read_text())
    same = (done.get("status") in FINISHED and done.get("max_steps") == int(max_steps)
            and (steps is None or done.get("steps") == steps)
            and stale_reason(done, data_id) is None)
    return done if same and (not evaluate or done.get("psnr") is not None) else None


def made_version(record: Mapping[str, Any]) -> int:
    """The :data:`METHOD_VERSION` a record was made with (1 when it does not say: records
    older than the field)."""
    return int(record.get("method_version") or 1)


def record_version(record: Mapping[str, Any], sizing: str | None = None) -> int:
    """The :data:`METHOD_VERSION` a ``metrics.json``, ``done.json`` or checkpoint meta stands
    for: the one it was made with (:func:`made_version`), carried over each later version
    that did not change runs of its ``sizing`` (:data:`VERSION_SCOPE`). A record that does
    not name its sizing is taken to be of ``sizing`` (the running job's, for its own
    segments and checkpoints), else changed.

    >>> record_version({"method_version": 3, "sizing": "cpu_ngp"}), record_version(
    ...     {"method_version": 3, "sizing": "cpu_nerf"}), record_version(
    ...     {"method_version": 4}, sizing="cpu_hexplane")
    (5, 3, 4)
    """
    version = made_version(record)
    sizing = record.get("sizing") or sizing
    while version < METHOD_VERSION:
        changed = VERSION_SCOPE.get(version + 1)
        if changed is None or sizing is None or changed(str(sizing)):
            break
        version += 1
    return version


def stale_reason(record: Mapping[str, Any], data_id: str | None) -> tuple[str, str] | None:
    """Why a record (``metrics.json``, ``done.json``, checkpoint meta) is stale for a run of
    this :data:`METHOD_VERSION` on the dataset ``data_id``: ``(tag, reason)``, e.g.
    ``("method_v1", "trained by method version 1 (now 2)")`` or ``("data_<id>", "trained
    on <id> (now <data_id>)")``; ``None`` if it is current. A record that names no dataset
    predates the field and is taken to match, as is any record when ``data_id`` is
    ``None`` (not known). A record that does not name its sizing is taken to be of the
    running job's (the Hydra choice; outside a Hydra app, of none)."""
    version = record_version(record, sizing_choice())
    if version != METHOD_VERSION:
        return f"method_v{version}", f"trained by method version {version} (now {METHOD_VERSION})"
    made_on = record.get("data_id")
    if data_id is not None and made_on is not None and made_on != data_id:
        return f"data_{made_on}", f"trained on {made_on} (now {data_id})"
    return None


# ---------------------------------------------------------------------------- done.json
def write_done(seg_dir: str | Path, max_steps: int, steps: int, wall_s: float,
               nonfinite_steps: int, opacity_log: Iterable[tuple[int, float]] = (),
               data_id: str | None = None) -> None:
    """Record a trained segment (``seg<k>/done.json``), with its logged mean opacity and
    the dataset it was trained on."""
    atomic_write_json(Path(seg_dir) / DONE_FILE, {
        "max_steps": int(max_steps), "steps": int(steps), "wall_s": float(wall_s),
        "nonfinite_steps": int(nonfinite_steps),
        "opacity_log": [[int(s), float(o)] for s, o in opacity_log],
        "method_version": METHOD_VERSION, "data_id": data_id, "sizing": sizing_choice()})


def read_done(seg_dir: str | Path, max_steps: int | None = None,
              current_method: bool = False, data_id: str | None = None) -> dict | None:
    """The segment's ``done.json`` (trained with exactly ``max_steps`` when given, and, if
    ``current_method``, by this :data:`METHOD_VERSION` on the dataset ``data_id``
    (:func:`stale_reason`): a sweep's "trained before"), else None."""
    path = Path(seg_dir) / DONE_FILE
    if not path.exists():
        return None
    done = json.loads(path.read_text())
    if current_method and stale_reason(done, data_id) is not None:
        return None
    return done if max_steps is None or int(done.get("max_steps", -1)) == max_steps else None


# ---------------------------------------------------------------------------- curve.csv
def _cell(value: Any) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return ""
    return f"{value:.5f}" if isinstance(value, float) else str(value)


class CurveLog:
    """Appends ``curve.csv`` rows of one segment as training goes (rank 0 only).

    >>> import tempfile
    >>> log = CurveLog(Path(tempfile.mkdtemp()) / "curve.csv")
    >>> log.append(1.5, 100, {"psnr": 24.0}, "cheap"); log.append(3.0, 200, {"psnr": 25.0}, "full")
    >>> log.truncate_after(100); [r["step"] for r in read_curve_rows(log.path)]
    ['100']
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def append(self, wall_s: float, step: int, row: Mapping[str, float | None],
               kind: str) -> None:
        """One row: training seconds, step, ``psnr/ssim/lpips`` (None → empty), kind."""
        new = not self.path.exists()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self.path.open("a", newline="") as f:
            w = csv.writer(f)
            if new:
                w.writerow(CURVE_HEADER)
            w.writerow([f"{wall_s:.3f}", step]
                       + [_cell(row.get(k)) for k in ("psnr", "ssim", "lpips")] + [kind])

    def truncate_after(self, step: int) -> None:
        """Drop rows logged after ``step`` (a resumed run logs them again), atomically."""
        if not self.path.exists():
            return
        rows = read_curve_rows(self.path)
        kept = [r for r in rows if int(r["step"]) <= step]
        if len(kept) != len(rows):
            write_curve(self.path, kept)


def read_curve_rows(path: str | Path) -> list[dict[str, str]]:
    """The rows of one ``curve.csv`` as dicts of strings (:class:`InputError` on a wrong
    header)."""
    path = Path(path)
    with path.open(newline="") as fh:
        reader = csv.DictReader(fh)
        missing = [k for k in CURVE_HEADER if k not in (reader.fieldnames or [])]
        if missing:
            raise InputError(path, "header", ",".join(CURVE_HEADER), reader.fieldnames)
        return [dict(r) for r in reader]


def write_curve(path: str | Path, rows: Iterable[Mapping[str, Any]]) -> Path:
    """Write rows with the :data:`CURVE_HEADER` keys (``None`` → empty cell), atomically."""
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(CURVE_HEADER)
    for r in rows:
        w.writerow(["" if r.get(k) is None else r.get(k) for k in CURVE_HEADER])
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, buf.getvalue().encode())
    return path


def stitch_curves(seg_dirs: Iterable[str | Path]) -> list[dict[str, str]]:
    """The segments' curves as one run: each segment's steps and seconds continue where
    the previous segment ended — at its ``done.json`` (steps, training seconds), or at
    its last row when it has none. Segments without a curve add only their offset.
    """
    rows: list[dict[str, str]] = []
    step0, wall0 = 0, 0.0
    for d in map(Path, seg_dirs):
        path = d / CURVE_FILE
        seg = read_curve_rows(path) if path.exists() else []
        for r in seg:
            rows.append(r | {"step": str(int(r["step"]) + step0),
                             "wall_s": f"{float(r['wall_s']) + wall0:.3f}"})
        done = read_done(d)
        if done is not None:
            step0 += int(done.get("steps", 0))
            wall0 += float(done.get("wall_s", 0.0))
        elif seg:
            step0 += max(int(r["step"]) for r in seg)
            wall0 += max(float(r["wall_s"]) for r in seg)
    return rows
