"""``qtl.bench.constraints``: crossings of declared bounds and the cost per search evaluation, on hand-made runs."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from qtl.bench.constraints import (
    Bound,
    bounds_of,
    constraint_figures,
    declared_bounds,
    episode_crossings,
    same_model_cost,
    search_seconds_per_evaluation,
)
from qtl.checkpoint import save_checkpoint
from qtl.loop import run as run_loop
from qtl.recorder import METRICS_FILE, TIMINGS_FILE
from tests.helpers import tiny_config

TRACK = [Bound(0, -0.5, 0.5)]


def states(*max_x: float, steps: int = 5) -> list[np.ndarray]:
    """One `steps+1 x 4` episode per value: x ramps from 0 to it, the other dimensions stay 0."""
    out = []
    for peak in max_x:
        s = np.zeros((steps + 1, 4))
        s[:, 0] = np.linspace(0.0, peak, steps + 1)
        out.append(s)
    return out


def row(kind: str, length: int, evaluations: str = "", crossed: str | None = None) -> dict[str, str]:
    r = {"kind": kind, "length": str(length), "policy_evaluations": evaluations}
    if crossed is not None:
        r["crossed"] = crossed
    return r


def test_a_bound_is_left_on_either_side_and_an_open_side_never() -> None:
    assert not Bound(0, -0.5, 0.5).left(states(0.5)[0])  # on the bound is inside
    assert Bound(0, -0.5, 0.5).left(states(0.51)[0]) and Bound(0, -0.5, 0.5).left(states(-0.51)[0])
    assert not Bound(0, None, 0.5).left(states(-9.0)[0]) and not Bound(0, -0.5, None).left(states(9.0)[0])
    assert not Bound(1, -0.1, 0.1).left(states(9.0)[0])  # another dimension


def test_bounds_of_a_constraints_list() -> None:
    declared = [{"dim": 0, "low": -2.4, "high": 2.4, "kind": "terminate"},
                {"dim": 2, "low": None, "high": 1.0, "kind": "penalty", "weight": 0.5}]
    assert bounds_of(declared) == [Bound(0, -2.4, 2.4), Bound(2, None, 1.0)]
    assert bounds_of([]) == []
    with pytest.raises(ValueError, match="needs a 'dim'"):
        bounds_of([{"low": 0.0}])


def test_crossings_against_bounds_come_from_the_states() -> None:
    rows = [row("random", 12), row("policy", 50), row("policy", 50)]
    # The states decide: the third crossed on its last step although its length is the full horizon.
    assert episode_crossings(rows, 50, states(7.0, 0.4, 0.6), TRACK) == [1, 0, 1]
    with pytest.raises(ValueError, match="states of all 3 episodes"):
        episode_crossings(rows, 50, states(7.0), TRACK)
    with pytest.raises(ValueError, match="states of all 3 episodes"):
        episode_crossings(rows, 50, None, TRACK)


def test_crossings_without_bounds_read_the_crossed_column_else_the_early_ends() -> None:
    recorded = [row("random", 12, crossed="1"), row("policy", 50, crossed="0"), row("policy", 50, crossed="1")]
    assert episode_crossings(recorded, 50) == [1, 0, 1]
    unrecorded = [row("random", 12), row("policy", 50), row("policy", 31)]
    assert episode_crossings(unrecorded, 50) == [1, 0, 1]
    partly = [row("random", 12, crossed=""), row("policy", 50, crossed="0")]  # an empty cell: the column is unusable
    assert episode_crossings(partly, 50) == [1, 0]
    assert episode_crossings([], 50) == []


def test_search_seconds_per_evaluation_over_the_learned_episodes() -> None:
    rows = [row("random", 50), row("policy", 50, "200"), row("policy", 50, "100")]
    timings = [{"policy_search_s": "0.0"}, {"policy_search_s": "4.0"}, {"policy_search_s": "2.0"}]
    assert search_seconds_per_evaluation(rows, timings) == pytest.approx(6.0 / 300)
    assert search_seconds_per_evaluation(rows[:1], timings[:1]) is None
    assert search_seconds_per_evaluation([row("policy", 50, "nan")], [{"policy_search_s": "1.0"}]) is None


def write_csv(path: Path, rows: list[dict]) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def test_constraint_figures_of_a_run_directory(tmp_path: Path) -> None:
    run = tmp_path / "seed_0"
    (run / ".hydra").mkdir(parents=True)
    (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"task": {"horizon": 5}}))
    write_csv(run / METRICS_FILE, [
        {"episode": 0, "kind": "random", "length": 3, "policy_evaluations": "", "predicted_survival": "nan"},
        {"episode": 1, "kind": "policy", "length": 5, "policy_evaluations": 40, "predicted_survival": 0.25},
        {"episode": 2, "kind": "policy", "length": 5, "policy_evaluations": 60, "predicted_survival": 0.75},
    ])
    write_csv(run / TIMINGS_FILE, [{"episode": e, "policy_search_s": s} for e, s in enumerate([0.0, 1.0, 3.0])])
    save_checkpoint(run, 2, {"dataset": {"states": [torch.as_tensor(s) for s in states(3.0, 0.4, 0.7)]}})

    figures = constraint_figures(run, 3, TRACK)
    assert figures["crossed"] == [1, 0, 1] and figures["crossings"] == 2  # the third crossed on its last step
    assert figures["lengths"] == [3, 5, 5]
    assert figures["predicted_survival"] == [None, 0.25, 0.75]
    assert figures["policy_evaluations"] == [None, 40.0, 60.0]
    assert figures["search_s_per_evaluation"] == pytest.approx(4.0 / 100)
    # Without bounds the early ends count: only the random episode.
    assert constraint_figures(run, 3, [])["crossed"] == [1, 0, 0]
    assert constraint_figures(run, 2, TRACK)["crossed"] == [1, 0]  # the first episodes only


def test_declared_bounds_of_the_shipped_tasks_and_of_the_switched_off_arm() -> None:
    assert declared_bounds(["task=cartpole_track"]) == [Bound(0, -0.7, 0.7)]
    assert declared_bounds(["task=cartpole_track", "task.constraints=[]"]) == []
    assert declared_bounds(["task=inverted_pendulum"]) == [Bound(1, -0.2, 0.2)]
    assert declared_bounds(["task=cartpole"]) == []


def test_same_model_cost_times_both_propagators_on_one_model(tmp_path: Path) -> None:
    run_loop(tiny_config("task=cartpole_track", "episodes=1"), tmp_path)
    cost = same_model_cost(tmp_path, repeats=1)
    assert cost["episode"] == 1 and cost["n"] > 0 and cost["repeats"] == 1
    assert cost["with_s"] > 0 and cost["without_s"] > 0
