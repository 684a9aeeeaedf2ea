"""Learning-curve summaries of Section 5: final performance, area under the curve, time to convergence."""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from qtl.recorder import METRICS_FILE

FINAL_EPISODES = 3  # final performance: mean total reward of the last 3 episodes
CONVERGED_FRACTION = 0.95  # time to convergence: first episode reaching 95 % of the final performance


def final_performance(returns: Sequence[float], last: int = FINAL_EPISODES) -> float:
    """Mean total reward of the last ``last`` episodes (Table 1)."""
    if len(returns) == 0:
        raise ValueError("a learning curve needs at least one episode")
    return float(np.mean(returns[-last:]))


def area_under_curve(returns: Sequence[float]) -> float:
    """Area under the learning curve by the trapezoidal rule over episodes, unit spacing (Table 2)."""
    values = np.asarray(returns, dtype=float)
    if values.size < 2:
        return float(values.sum())
    return float(np.trapezoid(values))


def time_to_convergence(returns: Sequence[float], fraction: float = CONVERGED_FRACTION) -> int:
    """First episode whose total reward reaches ``fraction`` of the final performance (Table 3)."""
    target = fraction * final_performance(returns)
    return next(i for i, r in enumerate(returns) if r >= target)


def first_success(successes: Sequence[bool | int]) -> int | None:
    """Index of the first successful episode (0 = the initial episode), or None."""
    return next((i for i, s in enumerate(successes) if s), None)


def relapses(successes: Sequence[bool | int]) -> int | None:
    """Episodes after the first success that fail the success test, or None without a success."""
    first = first_success(successes)
    return None if first is None else sum(not s for s in successes[first + 1:])


def final_successes(successes: Sequence[bool | int], last: int = FINAL_EPISODES) -> int:
    """Successful episodes among the last ``last`` (Table 1's episodes; 0 of them: the paper's "NC")."""
    if len(successes) == 0:
        raise ValueError("a learning curve needs at least one episode")
    return sum(bool(s) for s in successes[-last:])


@dataclass(frozen=True)
class Curve:
    """One run's learning curve, read from its ``metrics.csv``."""

    returns: list[float]
    successes: list[bool]
    compliance: list[float]  # NaN where not computed
    selected_source: list[float] = field(default_factory=list)  # k of the chosen source, several sources; else NaN

    @classmethod
    def read(cls, run_dir: str | os.PathLike, episodes: int | None = None) -> Curve:
        """The first ``episodes`` episodes of a run (all by default); runs are causal, so a prefix is a shorter run."""
        with open(Path(run_dir) / METRICS_FILE, newline="") as f:
            rows = list(csv.DictReader(f))
        if episodes is not None:
            if len(rows) < episodes:
                raise ValueError(f"{run_dir} has {len(rows)} episodes, {episodes} needed")
            rows = rows[:episodes]
        return cls(
            returns=[float(r["return"]) for r in rows],
            successes=[bool(int(r["success"])) for r in rows],
            compliance=[float(r.get("compliance") or "nan") for r in rows],
            selected_source=[float(r.get("selected_source") or "nan") for r in rows],
        )

    def chosen_source(self) -> int | None:
        """k of the source a run of several sources chose (its last episode's); None for other runs."""
        chosen = [k for k in self.selected_source if not math.isnan(k)]
        return int(chosen[-1]) if chosen else None

    def summary(self) -> dict[str, float | int | None]:
        """Final performance, AUC, time to convergence and first success of this curve."""
        return {
            "final_performance": final_performance(self.returns),
            "auc": area_under_curve(self.returns),
            "time_to_convergence": time_to_convergence(self.returns),
            "first_success": first_success(self.successes),
        }
