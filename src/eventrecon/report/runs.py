"""Run folders as the report reads them: collecting, copying and reading runs.

The files of a run folder (``metrics.json``, ``curve.csv``, ``seg<k>/``) are defined by
:mod:`eventrecon.results.records`; this module finds them (recursively, a malformed
``metrics.json`` is skipped with a one-line warning so the report of a sweep survives
one broken job), turns each into a :class:`Run`, reads curves as columns and copies a
committable record of a sweep. When ``metrics.json`` has no ``experiment``, an
``experiment=<name>`` override in ``.hydra/overrides.yaml`` names it.
"""

from __future__ import annotations

import logging
import math
import shutil
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from eventrecon.common.errors import InputError
from eventrecon.results.records import (
    CURVE_FILE,
    CURVE_HEADER,
    METRICS_FILE,
    VERSION_KEYS,
    made_version,
    read_curve_rows,
    read_metrics,
    record_version,
    stitch_curves,
    write_metrics,
)
from eventrecon.results.records import write_curve as _write_curve

log = logging.getLogger(__name__)

MODELS: tuple[str, ...] = ("nerf", "ngp", "tensorf_cp", "hexplane")


@dataclass
class Run:
    """One finished (or failed) run as read from its folder.

    ``metric(name)`` gives ``psnr``/``ssim``/``lpips`` as a float, or ``None`` when the
    value is absent (e.g. LPIPS unavailable). ``mtime`` orders reruns of the same cell.
    """

    path: Path
    scene: str
    model: str
    loss: str
    views: int | None  # None: "all views" (the config's null)
    fps: float | None  # None: "every RGB frame"
    status: str
    record: dict[str, Any] = field(repr=False)
    experiment: str | None = None
    mtime: float = 0.0

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def metric(self, name: str) -> float | None:
        v = self.record.get(name)
        if v is None:
            return None
        v = float(v)
        return None if math.isnan(v) else v

    @property
    def version(self) -> int:
        """The training method's version the run stands for: the ``method_version`` it was
        made with, carried over later versions that did not change its sizing
        (:func:`eventrecon.results.records.record_version`)."""
        return record_version(self.record)

    @property
    def versions(self) -> range:
        """The method versions the run trained as: from the one it was made with to
        :attr:`version`."""
        return range(made_version(self.record), self.version + 1)

    def shares_version(self, other: Run) -> bool:
        """Whether both runs trained as one method version (so a pair of them compares
        their settings, not a change of the method)."""
        return max(self.versions.start, other.versions.start) <= min(self.version,
                                                                        other.version)

    @property
    def recency(self) -> tuple[int, float]:
        """``(version, mtime)``: of two runs of one job or seed, the greater one replaces
        the other (a newer method version first, then the later file)."""
        return self.version, self.mtime

    def number(self, name: str) -> float | None:
        """A numeric field of ``metrics.json`` (``wall_s``, ``sec_per_it``, ...) or ``None``."""
        return self.metric(name)


def _experiment_from_hydra(folder: Path) -> str | None:
    path = folder / ".hydra" / "overrides.yaml"
    if not path.is_file():
        return None
    for line in path.read_text().splitlines():
        item = line.strip().lstrip("-").strip().strip("'\"")
        if item.startswith(("experiment=", "+experiment=")):
            return item.split("=", 1)[1].strip() or None
    return None


def read_run(folder: str | Path) -> Run:
    """Read ``<folder>/metrics.json``; :class:`InputError` on a malformed file."""
    folder = Path(folder)
    path = folder / METRICS_FILE
    rec = read_metrics(path)
    try:
        views = None if rec["views"] is None else int(rec["views"])
        fps = None if rec["fps"] is None else float(rec["fps"])
    except (TypeError, ValueError) as exc:
        raise InputError(path, "views/fps", "numbers", (rec["views"], rec["fps"])) from exc
    return Run(
        path=folder,
        scene=str(rec["scene"]),
        model=str(rec["model"]),
        loss=str(rec["loss"]),
        views=views,
        fps=fps,
        status=str(rec["status"]),
        record=rec,
        experiment=rec.get("experiment") or _experiment_from_hydra(folder),
        mtime=path.stat().st_mtime,
    )


def collect_runs(dirs: Iterable[str | Path]) -> list[Run]:
    """All runs under ``dirs`` (recursive search for ``metrics.json``), sorted by path.

    Missing folders and malformed files are logged and skipped.
    """
    runs: dict[Path, Run] = {}
    for d in dirs:
        d = Path(d)
        if not d.exists():
            log.warning("%s: no such folder (skipped)", d)
            continue
        files = [d / METRICS_FILE] if (d / METRICS_FILE).is_file() else []
        files += sorted(d.rglob(METRICS_FILE))
        for f in files:
            key = f.parent.resolve()
            if key in runs:
                continue
            try:
                runs[key] = read_run(f.parent)
            except InputError as exc:
                log.warning("skipped run: %s", exc)
    return sorted(runs.values(), key=lambda r: str(r.path))


#: A run's job: the fields of its record that say what was trained (not how it went).
JOB_KEYS: tuple[str, ...] = ("scene", "model", "loss", "views", "fps", "seed", "tag",
                             "schedule", "skip", "sizing", "lr_end_factor",
                             "lr_warmup", "lr_decay_start", "betas_power",
                             "max_steps")
#: Values a record written before its key existed stands for.
_JOB_DEFAULTS: dict[str, Any] = {"lr_end_factor": 1.0, "lr_warmup": 0, "lr_decay_start": 0.0,
                                 "betas_power": 1.0}


def supersedes(new: Run, old: Run) -> bool:
    """Whether ``new`` replaces ``old`` in the tables: a run of the same experiment and job
    (:data:`JOB_KEYS`) made with a newer method version. The job keys whose default a
    version after ``old``'s changed (:data:`eventrecon.results.records.VERSION_KEYS`) may differ:
    a version-4 run with ``betas_power`` 10 replaces the version-3 run of its job, which
    trained with the old default 1."""
    if new.version <= old.version:
        return False
    free = {k for v in range(old.version + 1, new.version + 1) for k in VERSION_KEYS.get(v, ())}
    return _job(new, free) == _job(old, free)


def current_runs(runs: Iterable[Run]) -> list[Run]:
    """The runs not superseded (:func:`supersedes`), so a table never mixes a job's stale
    and fresh records. Order is kept."""
    runs = list(runs)
    free = {k for keys in VERSION_KEYS.values() for k in keys}
    keys = [_job(r, free) for r in runs]
    groups: dict[tuple, list[Run]] = {}
    for r, key in zip(runs, keys):
        groups.setdefault(key, []).append(r)
    kept = [r for r, key in zip(runs, keys) if not any(supersedes(s, r) for s in groups[key])]
    if len(kept) < len(runs):
        log.info("%d run(s) superseded by a newer method version of the same job",
                 len(runs) - len(kept))
    return kept


def versions_markdown(runs: Iterable[Run]) -> str:
    """One line per experiment: how many of its runs each method version made, e.g.
    ``- table3: 165 runs of method version 1`` (findings pair runs of one experiment, so
    this says which method each finding measured)."""
    by_exp: dict[str, dict[int, int]] = {}
    for r in runs:
        counts = by_exp.setdefault(r.experiment or "(no experiment)", {})
        counts[r.version] = counts.get(r.version, 0) + 1
    lines = [f"- {exp}: " + ", ".join(f"{n} run{'s' * (n != 1)} of method version {v}"
                                      for v, n in sorted(counts.items()))
             for exp, counts in sorted(by_exp.items())]
    return "## Runs by method version\n\n" + "\n".join(lines) + "\n" if lines else ""


def _job(r: Run, skip: set[str] | frozenset[str] = frozenset()) -> tuple:
    """``r``'s experiment and :data:`JOB_KEYS` values (``None`` for the keys in ``skip``)."""
    return (r.experiment, *(None if k in skip else str(r.record.get(k, _JOB_DEFAULTS.get(k)))
                            for k in JOB_KEYS))


def copy_runs(runs: Iterable[Run], roots: Iterable[str | Path], dest: str | Path) -> list[Path]:
    """Copy each run's ``metrics.json`` and ``curve.csv`` (with their times) to
    ``dest/<root name>/<path below the root>/``: a small, committable record from which
    the tables and the accuracy-vs-time figure can be regenerated. Returns the folders."""
    roots = [Path(r).resolve() for r in roots]
    names = {}
    for i, r in enumerate(roots):  # two roots of the same name get distinct folders
        names[r] = r.name if [x.name for x in roots].count(r.name) == 1 else f"{r.name}-{i}"
    out = []
    for run in runs:
        src = Path(run.path).resolve()
        root = next((r for r in roots if src == r or r in src.parents), src.parent)
        target = Path(dest) / names.get(root, root.name) / src.relative_to(root)
        target.mkdir(parents=True, exist_ok=True)
        for name in (METRICS_FILE, CURVE_FILE):
            if (src / name).is_file():
                shutil.copy2(src / name, target / name)
        out.append(target)
    return out


def prune_superseded(dest: str | Path) -> list[Path]:
    """Delete the records below ``dest`` (a :func:`copy_runs` copy) that newer runs of their
    job supersede (:func:`current_runs`): their ``metrics.json`` and ``curve.csv``, and the
    folder once empty. Returns the folders pruned (git history keeps committed records)."""
    runs = collect_runs([dest])
    kept = {id(r) for r in current_runs(runs)}
    pruned = []
    for run in runs:
        if id(run) in kept:
            continue
        for name in (METRICS_FILE, CURVE_FILE):
            (run.path / name).unlink(missing_ok=True)
        if not any(run.path.iterdir()):
            run.path.rmdir()
        log.info("pruned %s: superseded by a newer method version of its job", run.path)
        pruned.append(run.path)
    return pruned


def read_curve(folder: str | Path) -> dict[str, np.ndarray]:
    """``<folder>/curve.csv`` (or its segments' curves, stitched by
    :func:`eventrecon.results.records.stitch_curves`) as columns: float arrays ``wall_s, step,
    psnr, ssim, lpips`` (empty cell → NaN) and a str array ``kind``, sorted by
    ``wall_s``. Missing file → empty columns; a malformed cell → :class:`InputError`.
    """
    folder = Path(folder)
    top = folder / CURVE_FILE
    if top.is_file():
        rows, path = read_curve_rows(top), top
    else:
        segs = sorted(folder.glob("seg*/"), key=lambda p: (len(p.name), p.name))
        rows, path = stitch_curves(segs), folder
    cols: dict[str, list] = {k: [] for k in CURVE_HEADER}
    for i, row in enumerate(rows, start=2):
        for k in CURVE_HEADER[:-1]:
            cell = (row[k] or "").strip()
            try:
                cols[k].append(float(cell) if cell else math.nan)
            except ValueError as exc:
                raise InputError(path, f"line {i} {k}", "a number", cell) from exc
        cols["kind"].append((row["kind"] or "full").strip())
    return _as_columns(cols)


def empty_curve() -> dict[str, np.ndarray]:
    """A curve with no rows (the columns of :func:`read_curve`)."""
    return _as_columns({k: [] for k in CURVE_HEADER})


def run_curve(run: Run) -> dict[str, np.ndarray]:
    """``run``'s curve (:func:`read_curve`); a malformed ``curve.csv`` is logged as one
    warning and read as empty, so that one broken record does not stop a report."""
    try:
        return read_curve(run.path)
    except InputError as exc:
        log.warning("ignored curve: %s", exc)
        return empty_curve()


def _as_columns(cols: dict[str, list]) -> dict[str, np.ndarray]:
    out = {k: np.asarray(v, dtype=float) for k, v in cols.items() if k != "kind"}
    out["kind"] = np.asarray(cols["kind"], dtype=str)
    order = np.argsort(out["wall_s"], kind="stable")
    return {k: v[order] for k, v in out.items()}


def write_run(
    folder: str | Path,
    metrics: Mapping[str, Any],
    curve: Iterable[Mapping[str, Any]] = (),
) -> Path:
    """Write ``metrics.json`` (and ``curve.csv`` from rows with the CURVE_HEADER keys)
    through :mod:`eventrecon.results.records`. Returns the folder (demo sweeps and tests)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    write_metrics(folder, metrics)
    rows = list(curve)
    if rows:
        _write_curve(folder / CURVE_FILE, rows)
    return folder


def write_curve(path: str | Path, rows: Iterable[Mapping[str, Any]]) -> Path:
    """Write curve rows (keys of ``CURVE_HEADER``; ``None`` → empty cell) as CSV."""
    return _write_curve(path, rows)
