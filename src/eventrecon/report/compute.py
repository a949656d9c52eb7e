"""What the tables cost to make: each sweep's job times and the time still owed.

A job's time is its record's ``total_s`` (the whole process: dataset, training,
evaluation; ``wall_s``, training alone, where an older record lacks it). A resumed job
counts its last process only, so a sum is a lower bound when jobs were killed and resumed.

For each experiment, over the runs made with the current
:data:`~eventrecon.results.records.METHOD_VERSION`:

- ``n`` runs, their median job time ``m`` and total ``S = Σ total_s``;
- the sweep's wall time on ``lanes`` parallel one-thread jobs, ``S / lanes`` (the recipe
  in ``docs/results``: two one-thread jobs on the two cores, so each job's time already
  includes sharing the machine);
- the runs still of an older method version (``k``, to be re-run) and what re-running
  them would take, ``Σ m_r / lanes``: each priced at the median job time of the current
  runs of its experiment and model, else of its model in any experiment (a backbone's
  job time differs far more between backbones than between experiments), else at the
  median of its experiment's older runs of that model.
"""

from __future__ import annotations

import statistics
from collections.abc import Iterable
from dataclasses import dataclass

from eventrecon.report.format import fmt, markdown_table
from eventrecon.report.runs import Run
from eventrecon.results.records import METHOD_VERSION

__all__ = ["LANES", "SweepCost", "job_seconds", "sweep_costs", "sweep_costs_markdown"]

#: Parallel one-thread jobs of the sweep recipe on a 2-core machine.
LANES: int = 2


@dataclass(frozen=True)
class SweepCost:
    """The cost of one experiment's runs (module docstring)."""

    experiment: str
    runs: int            # current-version runs with a job time
    median_s: float      # their median job time (nan when runs == 0)
    total_s: float       # the sum of their job times
    stale: int           # runs of an older method version, to be re-run
    owed_s: float = 0.0  # re-running them on ``lanes`` lanes (module docstring)
    lanes: int = LANES

    @property
    def wall_s(self) -> float:
        """The current-version runs' sweep time on ``lanes`` lanes: ``total_s / lanes``."""
        return self.total_s / self.lanes


def job_seconds(run: Run) -> float | None:
    """The run's job time in seconds: ``total_s``, else ``wall_s``, else ``None``."""
    for key in ("total_s", "wall_s"):
        v = run.number(key)
        if v is not None:
            return v
    return None


def sweep_costs(runs: Iterable[Run], lanes: int = LANES) -> list[SweepCost]:
    """One :class:`SweepCost` per experiment of ``runs`` (the report's current runs),
    sorted by name."""
    current: dict[tuple[str, str], list[float]] = {}   # (experiment, model) -> job times
    older: dict[tuple[str, str], list[float]] = {}
    stale: dict[tuple[str, str], int] = {}
    for r in runs:
        key = (r.experiment or "(no experiment)", r.model)
        current.setdefault(key, [])
        t = job_seconds(r)
        if r.version != METHOD_VERSION:
            stale[key] = stale.get(key, 0) + 1
            older.setdefault(key, []).extend([] if t is None else [t])
        elif t is not None:
            current[key].append(t)
    by_model: dict[str, list[float]] = {}
    for (_, model), ts in current.items():
        by_model.setdefault(model, []).extend(ts)

    def price(key: tuple[str, str]) -> float:
        for ts in (current[key], by_model[key[1]], older.get(key, [])):
            if ts:
                return statistics.median(ts)
        return float("nan")

    out = []
    for exp in sorted({e for e, _ in current}):
        ts = [t for (e, _), v in current.items() if e == exp for t in v]
        owed = sum(n * price(k) for k, n in stale.items() if k[0] == exp)
        out.append(SweepCost(exp, len(ts), _median(ts), sum(ts), sum(
            n for k, n in stale.items() if k[0] == exp), owed / lanes, lanes))
    return out


def _median(values: list[float]) -> float:
    return statistics.median(values) if values else float("nan")


def _hours(seconds: float) -> str:
    return fmt(seconds / 3600, 2)


def sweep_costs_markdown(costs: list[SweepCost]) -> str:
    """The costs as a Markdown section with a total row ("" when there are none)."""
    if not costs:
        return ""
    lanes = costs[0].lanes
    rows = [[f"`{c.experiment}`", str(c.runs),
             fmt(c.median_s / 60, 1), _hours(c.total_s),
             _hours(c.wall_s), str(c.stale), _hours(c.owed_s)] for c in costs]
    rows.append(["all", str(sum(c.runs for c in costs)), "", _hours(sum(c.total_s for c in costs)),
                 _hours(sum(c.wall_s for c in costs)), str(sum(c.stale for c in costs)),
                 _hours(sum(c.owed_s for c in costs))])
    header = ["sweep", f"runs (v{METHOD_VERSION})", "median job (min)", "Σ job time (h)",
              f"on {lanes} lanes (h)", "older runs", f"their re-run on {lanes} lanes (h)"]
    note = (f"Job time: `total_s` (dataset, training, evaluation) of each version-"
            f"{METHOD_VERSION} run. {lanes} lanes: one-thread jobs side by side on the 2 "
            "cores, as the sweeps run, so each job's time includes the sharing. A job "
            "resumed after a kill counts its last process only. Older runs: records of an "
            "earlier method version, each re-run at the median job time of the current runs "
            "of its sweep and backbone (of its backbone in any sweep where its sweep has "
            "none; the older runs' own median where no current run of its backbone exists).")
    return f"## What the sweeps cost\n\n{markdown_table(header, rows)}\n\n- {note}\n"
