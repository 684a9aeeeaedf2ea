"""A learning run's figures about state constraints (issue 64): which episodes crossed a bound, what a search step cost.

The crossings of two runs are only comparable when they are counted against the same bounds: a run with its
constraints switched off (``task.constraints=[]``) declares none, so its ``crossed`` column cannot say that its
cart left the track. :func:`episode_crossings` therefore counts, in this order of preference, against the bounds it
is given (the real episodes' states, from the run's newest checkpoint), from the ``crossed`` column of
``metrics.csv``, or, where neither is at hand, the episodes the env ended before the horizon.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from qtl.bench.runs import read_csv
from qtl.build import build
from qtl.checkpoint import run_checkpoint
from qtl.config import checked_task, register_configs
from qtl.recorder import METRICS_FILE, TIMINGS_FILE
from qtl.runs import load_run, with_overrides

CROSSED_COLUMN = "crossed"  # metrics.csv: 1 if the real episode's states left a declared bound


@dataclass(frozen=True)
class Bound:
    """One declared state bound: ``low <= x[dim] <= high``, ``None`` for an open side."""

    dim: int
    low: float | None = None
    high: float | None = None

    @classmethod
    def from_config(cls, entry: Mapping) -> Bound:
        """A bound from one ``task.constraints`` entry (``dim``, ``low``, ``high``; ``kind`` and ``weight`` unused)."""
        if "dim" not in entry:
            raise ValueError(f"a constraint needs a 'dim', got {dict(entry)!r}")
        low, high = entry.get("low"), entry.get("high")
        return cls(int(entry["dim"]), None if low is None else float(low), None if high is None else float(high))

    def left(self, states: np.ndarray) -> bool:
        """Whether any of the `T x D` ``states`` lies outside the bound."""
        x = np.asarray(states, dtype=float)[:, self.dim]
        below = self.low is not None and bool(np.any(x < self.low))
        return below or (self.high is not None and bool(np.any(x > self.high)))


def bounds_of(constraints: Sequence[Mapping]) -> list[Bound]:
    """The bounds of a ``task.constraints`` list (every kind: ``crossed`` counts any declared bound)."""
    return [Bound.from_config(entry) for entry in constraints]


def episode_crossings(rows: Sequence[Mapping[str, str]], horizon: int,
                      states: Sequence[np.ndarray] | None = None, bounds: Sequence[Bound] = ()) -> list[int]:
    """Per episode of ``rows`` (metrics.csv), 1 if it crossed a bound, else 0.

    With ``bounds`` and the episodes' ``states`` (`T+1 x D` each): whether a state left one of them. Otherwise the
    ``crossed`` column where the run recorded it, else whether the env ended the episode before ``horizon`` steps
    (``length``): an episode ended on its last step by a crossing then counts as not crossed.
    """
    if bounds:
        if states is None or len(states) < len(rows):
            given = 0 if states is None else len(states)
            raise ValueError(f"bounds need the states of all {len(rows)} episodes, got {given}")
        return [int(any(bound.left(episode) for bound in bounds)) for episode in states[: len(rows)]]
    if rows and all(row.get(CROSSED_COLUMN) not in (None, "") for row in rows):
        return [int(float(row[CROSSED_COLUMN])) for row in rows]
    return [int(int(row["length"]) < horizon) for row in rows]


def search_seconds_per_evaluation(rows: Sequence[Mapping[str, str]],
                                  timings: Sequence[Mapping[str, str]]) -> float | None:
    """Policy-search seconds per evaluation of the predicted return over the learned episodes (None: none recorded).

    ``timings.csv``'s ``policy_search_s`` summed, over ``metrics.csv``'s ``policy_evaluations`` summed, both over
    the episodes of kind ``policy``.
    """
    seconds, evaluations = 0.0, 0.0
    for row, timing in zip(rows, timings, strict=False):
        count = row.get("policy_evaluations") or ""
        if row.get("kind") != "policy" or not count or math.isnan(float(count)):
            continue
        seconds += float(timing["policy_search_s"])
        evaluations += float(count)
    return seconds / evaluations if evaluations else None


def episode_states(run_dir: Path, episodes: int) -> list[np.ndarray]:
    """The real states (`T+1 x D` each) of a run's first ``episodes`` episodes, from its newest checkpoint."""
    dataset = run_checkpoint(run_dir)["dataset"]
    return [np.asarray(s, dtype=float) for s in dataset["states"][:episodes]]


def constraint_figures(run_dir: Path, episodes: int, bounds: Sequence[Bound]) -> dict:
    """A finished run's crossings per episode (against ``bounds``, see :func:`episode_crossings`) and search cost."""
    rows = read_csv(run_dir / METRICS_FILE)[:episodes]
    timings = read_csv(run_dir / TIMINGS_FILE)[:episodes]
    horizon = int(OmegaConf.load(run_dir / ".hydra" / "config.yaml").task.horizon)
    states = episode_states(run_dir, episodes) if bounds else None
    crossed = episode_crossings(rows, horizon, states, bounds)
    return {
        "lengths": [int(row["length"]) for row in rows],
        "crossed": crossed,
        "crossings": sum(crossed),
        "recorded_crossed": [_number(row.get(CROSSED_COLUMN)) for row in rows],
        "predicted_survival": [_number(row.get("predicted_survival")) for row in rows],
        "policy_evaluations": [_number(row.get("policy_evaluations")) for row in rows],
        "search_s_per_evaluation": search_seconds_per_evaluation(rows, timings),
    }


def _number(cell: str | None) -> float | None:
    """A metrics.csv cell as a number; None where it is absent, empty or nan (JSON has no nan)."""
    if cell in (None, ""):
        return None
    value = float(cell)
    return None if math.isnan(value) else value


def declared_bounds(overrides: Sequence[str]) -> list[Bound]:
    """The bounds ``task.constraints`` declares in the ``train`` config composed with ``overrides``.

    The task is checked as ``qtl-train`` checks it (:func:`qtl.config.checked_task`), so a bad override fails here,
    before any run, with Hydra's or the task's one-line error.
    """
    register_configs()
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        cfg = compose(config_name="train", overrides=list(overrides))
    task = OmegaConf.to_container(cfg.task, resolve=True)
    checked_task(task)  # type: ignore[arg-type]
    return bounds_of(task.get("constraints") or [])  # type: ignore[union-attr]


def same_model_cost(run_dir: Path, repeats: int = 7, seed: int = 0) -> dict:
    """One rollout + gradient with and without the run's constraints on the same model, ψ and start: median s.

    The model is fitted (``seed``) to the run's data after its last episode, ψ is its last policy; the two
    propagators alternate, ``repeats`` times each after a warm-up, so both see the same machine.
    """
    run = load_run(run_dir)
    arms = {"with": run.parts, "without": build(with_overrides(run.config, ["task.constraints=[]"]))}
    data = run.dataset()
    model = run.parts.fit_dynamics(data, torch.Generator().manual_seed(seed))
    policy = run.policy()
    task = run.parts.task
    propagators = {arm: parts.make_propagator(model, policy, parts.reward, angle_dims=task.angle_dims)
                   for arm, parts in arms.items()}
    times: dict[str, list[float]] = {arm: [] for arm in arms}
    for _ in range(repeats + 1):  # the first of each is a warm-up
        for arm, propagator in propagators.items():
            policy.zero_grad()
            tic = time.perf_counter()
            propagator.expected_return(run.parts.start, task.horizon).backward()
            times[arm].append(time.perf_counter() - tic)
    return {"n": len(data), "episode": run.episode, "repeats": repeats,
            **{f"{arm}_s": statistics.median(t[1:]) for arm, t in times.items()}}
