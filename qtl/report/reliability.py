"""Reliability over every run of an experiment, sources and targets: the numerical trouble of ``health.csv`` summed.

Each run's ``health.csv`` (:mod:`qtl.health`) holds per episode the counts of non-finite objectives, failed
factorisations, policy-search runs stopped at an invalid ψ, Cholesky jitter and failed GP-fit restarts, and
whether the episode began a resumed session. Runs made before ``health.csv`` existed count as not recorded.
A run with fewer episodes than its configuration asks for is unfinished: interrupted, still running, or failed.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from qtl.health import EVENTS
from qtl.recorder import HEALTH_FILE
from qtl.report.discover import Experiment, configured_episodes
from qtl.report.tables import markdown

# The columns of the reliability table, as its rows name them.
EVENT_NAMES = {
    "nonfinite_objectives": "non-finite objectives (value or gradient)",
    "linalg_failures": "failed factorisations in a rollout",
    "search_runs_stopped": "policy-search runs stopped early at an invalid ψ",
    "cholesky_jitter": "Cholesky factorisations retried with jitter",
    "gp_fit_failures": "GP-fit failures (a restart discarded, or L-BFGS resumed from its best θ)",
    "constant_outputs": "outputs with a constant Δ, modelled as deterministic (per model fit)",
}


@dataclass
class Reliability:
    """The counts of a set of runs: events summed, resumed sessions, and the runs that are unfinished."""

    runs: int = 0
    episodes: int = 0
    recorded: int = 0  # episodes with a health.csv row
    events: dict[str, int] = field(default_factory=lambda: dict.fromkeys(EVENTS, 0))
    resumed: int = 0  # sessions that continued a run from a checkpoint
    resumed_runs: int = 0
    unfinished: list[str] = field(default_factory=list)  # run dirs with fewer episodes than configured

    def add(self, run_dir: Path, episodes: int, name: str) -> None:
        """Add one run of ``episodes`` episodes (its metrics.csv rows)."""
        self.runs += 1
        self.episodes += episodes
        rows = _health_rows(run_dir)
        self.recorded += len(rows)
        for event in EVENTS:
            self.events[event] += sum(int(r.get(event) or 0) for r in rows)
        resumed = sum(int(r.get("resumed") or 0) for r in rows)
        self.resumed += resumed
        self.resumed_runs += int(resumed > 0)
        configured = configured_episodes(run_dir)
        if configured is not None and episodes < configured:
            self.unfinished.append(f"{name} ({episodes} of {configured})")


def _health_rows(run_dir: Path) -> list[dict[str, str]]:
    path = run_dir / HEALTH_FILE
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def reliability(experiment: Experiment) -> dict[str, Reliability]:
    """{"source": ..., "target": ..., "all": ...}: the counts of the source runs, of the target runs, of both."""
    parts = {"source": Reliability(), "target": Reliability(), "all": Reliability()}
    for seed, run_dir in experiment.source_dirs.items():
        for part in ("source", "all"):
            parts[part].add(run_dir, len(experiment.sources[seed].returns), f"source/seed_{seed}")
    for approach, by_label in experiment.cells.items():
        for label, cell in by_label.items():
            for seed in cell.seeds:
                for part in ("target", "all"):
                    parts[part].add(cell.run_dirs[seed], cell.lengths[seed], f"{approach}/{label}/seed_{seed}")
    return parts


def reliability_markdown(experiment: Experiment) -> str:
    """The reliability table: one column per part (source, target, all), one row per count; unfinished runs listed."""
    parts = reliability(experiment)
    rows = [
        ["runs", *(str(p.runs) for p in parts.values())],
        ["episodes (with a health record)", *(f"{p.episodes} ({p.recorded})" for p in parts.values())],
        *([EVENT_NAMES[e], *(str(p.events[e]) for p in parts.values())] for e in EVENTS),
        ["resumed sessions (runs)", *(f"{p.resumed} ({p.resumed_runs})" for p in parts.values())],
        ["unfinished runs (fewer episodes than configured)", *(str(len(p.unfinished)) for p in parts.values())],
    ]
    table = pd.DataFrame(rows, columns=["count", "source runs", "target runs", "all"])
    text = markdown(table)
    unfinished = parts["all"].unfinished
    if unfinished:
        text += "\n\nUnfinished: " + ", ".join(unfinished) + "."
    return text


def reliability_json(experiment: Experiment) -> dict[str, dict[str, object]]:
    """The counts of :func:`reliability` as plain data, for ``tables.json``."""
    return {part: {"runs": r.runs, "episodes": r.episodes, "recorded_episodes": r.recorded, **r.events,
                   "resumed_sessions": r.resumed, "resumed_runs": r.resumed_runs, "unfinished": r.unfinished}
            for part, r in reliability(experiment).items()}
