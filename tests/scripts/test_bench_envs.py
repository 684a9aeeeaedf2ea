"""``scripts/bench_envs.py``: its verdict, its merged results and its table, on fake runs (no learning)."""

from __future__ import annotations

import csv
from pathlib import Path

import yaml

from qtl.recorder import METRICS_FILE, TIMINGS_FILE
from tests.report.fakes import table_rows
from tests.scripts.load import script

bench_envs = script("bench_envs")

ROOT = Path(__file__).resolve().parents[2]

TASK = {"horizon": 40, "action_repeat": 5, "success": {"threshold": 0.05, "last_steps": 1}}


def seed_result(seed: int, first: int | None) -> dict:
    return {"seed": seed, "first_success": first, "returns": [0.0, 1.5], "lengths": [40, 18],
            "env_returns": [-0.5, 95.3], "learning_s": 12.0, "wall_s": 0.0,
            "success_test": bench_envs.success_test(TASK)}


def env_result(firsts: list[int | None], within: int = 10) -> dict:
    per_seed = [seed_result(seed, first) for seed, first in enumerate(firsts)]
    machine = {"cpu": "test CPU", "cores": 2, "torch": "2.13.0"}
    return {"date": "2026-11-23", "commit": "abc1234", "command": "python scripts/bench_envs.py", "machine": machine,
            "overrides": [], "jobs": 2, "threads": 1, "within": within, "episodes_per_run": within,
            "success_test": per_seed[0]["success_test"], "verdict": bench_envs.verdict(per_seed, within, within),
            "per_seed": per_seed}


def test_every_example_has_a_task_file_and_says_what_its_success_means():
    for name in bench_envs.EXAMPLES:
        assert (ROOT / "configs" / "task" / f"{name}.yaml").is_file()
        assert bench_envs.MEANINGS[name]


def test_the_verdict_needs_two_of_three_seeds_within_the_budget():
    assert bench_envs.verdict([seed_result(0, 3), seed_result(1, 9), seed_result(2, None)], 10, 10)["passed"]
    # Episode 10 is the eleventh episode: outside the 10 asked for, even when the runs went on.
    failed = bench_envs.verdict([seed_result(0, 3), seed_result(1, 10), seed_result(2, None)], 10, 12)
    assert failed == {"solved": 1, "seeds": 3, "passed": False}
    assert bench_envs.verdict([seed_result(0, 1), seed_result(1, 2)], 10, 10)["passed"] is None  # too few seeds
    unjudged = [seed_result(0, None), seed_result(1, None), seed_result(2, None)]
    assert bench_envs.verdict(unjudged, 10, 2)["passed"] is None  # runs shorter than the budget: not judged


def test_results_of_examples_not_run_now_are_kept_and_the_table_judges_each():
    previous = {"envs": {"inverted_pendulum": env_result([None, None, 4]), "pendulum": env_result([9, 9, 9])}}
    merged = bench_envs.merge(previous, {"pendulum": env_result([2, None, 5]), "mountaincar_continuous":
                                         env_result([1, 1])})
    assert list(merged["envs"]) == ["pendulum", "mountaincar_continuous", "inverted_pendulum"]  # EXAMPLES' order
    assert [r["first_success"] for r in merged["envs"]["pendulum"]["per_seed"]] == [2, None, 5]
    text = bench_envs.table(merged)
    sections = text.split("### ")[1:]
    assert [s.splitlines()[0] for s in sections] == list(merged["envs"])
    assert "— met (2 of 3 seeds succeeded)" in sections[0]
    assert "not judged" in sections[1] and "— NOT met (1 of 3 seeds succeeded)" in sections[2]
    assert ("1", "—", "0.0 1.5", "40 18", "95.3", "12", "reused") in table_rows(sections[0])
    assert "<= 0.05 for the last 1 of 40 steps, each step 5 env steps" in sections[0]


def test_a_run_directory_gives_lengths_learning_time_and_the_success_test(tmp_path):
    (tmp_path / ".hydra").mkdir()
    (tmp_path / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"seed": 0, "task": TASK}))
    metrics = [{"length": 40, "env_return": -4.0}, {"length": 17, "env_return": 93.5}, {"length": 12, "env_return": 0}]
    for name, rows in ((METRICS_FILE, metrics),
                       (TIMINGS_FILE, [{"model_fit_s": 0.0, "policy_search_s": 0.0},
                                       {"model_fit_s": 1.5, "policy_search_s": 2.5},
                                       {"model_fit_s": 9.0, "policy_search_s": 9.0}])):
        with open(tmp_path / name, "w", newline="") as f:
            writer = csv.DictWriter(f, list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
    described = bench_envs.describe_run(tmp_path, budget=2)  # only the episodes within the budget
    assert described["lengths"] == [40, 17] and described["learning_s"] == 4.0
    assert described["env_returns"] == [-4.0, 93.5]
    assert described["success_test"].startswith("distance to the target in the reward's metric <= 0.05")
