"""What the tables cost to make: each sweep's job times and the time still owed.

A job's time is its record's ``total_s`` (the whole process: dataset, training,
evaluation; ``wall_s``, training alone, where an older record lacks it). A resumed job
counts its last process only, so a sum is a lower bound when jobs were killed and resumed.

For each experiment, over the runs made with the current
:data:`~eventrecon.records.METHOD_VERSION`:

- ``n`` runs, their median job time ``m`` and total ``S = Σ total_s``;
- the sweep's wall time on ``lanes`` parallel one-thread jobs, ``S / lanes`` (the recipe
  in ``docs/results``: two one-thread jobs on the two cores, so each job's time already
  includes sharing the machine);
- the runs still of an older method version (``k``, to be re-run) and what re-running
  them would take at the same median, ``k · m / lanes`` (at the older runs' own median
  while no current run gives one).
"""

from __future__ import annotations

import statistics
from collections.abc import Iterable
from dataclasses import dataclass

from eventrecon.records import METHOD_VERSION
from eventrecon.report.format import fmt, markdown_table
from eventrecon.report.runs import Run

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
    stale_median_s: float = float("nan")   # the older runs' median job time
    lanes: int = LANES

    @property
    def wall_s(self) -> float:
        """The current-version runs' sweep time on ``lanes`` lanes: ``total_s / lanes``."""
        return self.total_s / self.lanes

    @property
    def owed_s(self) -> float:
        """Re-running the stale runs: ``stale · median_s / lanes``, with the older runs'
        median where there is no current one (0 when nothing is stale)."""
        if not self.stale:
            return 0.0
        median = self.median_s if self.runs else self.stale_median_s
        return self.stale * median / self.lanes


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
    times: dict[str, list[float]] = {}
    older: dict[str, list[float | None]] = {}
    for r in runs:
        exp = r.experiment or "(no experiment)"
        times.setdefault(exp, [])
        older.setdefault(exp, [])
        if r.version != METHOD_VERSION:
            older[exp].append(job_seconds(r))
        elif (t := job_seconds(r)) is not None:
            times[exp].append(t)
    return [SweepCost(exp, len(ts), _median(ts), sum(ts), len(older[exp]),
                      _median([t for t in older[exp] if t is not None]), lanes)
            for exp, ts in sorted(times.items())]


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
            "earlier method version, re-run at the current runs' median job time (the older "
            "runs' own median where there is no current run).")
    return f"## What the sweeps cost\n\n{markdown_table(header, rows)}\n\n- {note}\n"
