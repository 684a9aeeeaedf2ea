"""The sample-transfer benchmark's logic: the arms' overrides, a run's figures, the pairing and the goals."""

from __future__ import annotations

import pytest

from qtl.bench.record import machine
from qtl.bench.samples import (
    ARMS,
    SETTINGS,
    auc_pairs,
    comparisons,
    first_success_pairs,
    goal_a,
    goal_b,
    run_result,
    section,
)

BUDGET = 8


def fake(seed: int, first: int | None, auc: float = 100.0) -> dict:
    """A finished run's figures as the benchmark reads them (only what the logic uses)."""
    return {"seed": seed, "first_success": first, "auc": auc, "final_performance": auc / BUDGET,
            "returns": [auc / (BUDGET - 1)] * BUDGET, "relevance": [None, 0.5], "last_relevance": 0.5,
            "last_effective_samples": 100.0, "model_fit_s_per_episode": 1.0, "policy_search_s_per_episode": 10.0}


def test_each_arm_runs_the_target_with_its_own_transfer():
    setting = SETTINGS["cartpole-1.0"]
    runs = {arm: setting.target_overrides(arm, 3, "src", ["x=1"]) for arm in ARMS}
    common = ["task=cartpole", "task.env.pole_mass=1", "seed=3", "episodes=7", "optimizer.restarts=1"]
    assert runs["pilco"] == [*common, "x=1"]
    assert runs["qtl_bayesian"] == [*common, "approach=qtl_bayesian", "transfer.source=src", "x=1"]
    assert runs["qtl_bayesian_samples"] == [*common, "approach=qtl_bayesian", "transfer.samples=relevance",
                                            "transfer.source=src", "x=1"]
    assert runs["samples"] == [*common, "rule=none", "transfer.hyperparameters=false", "transfer.samples=relevance",
                               "transfer.source=src", "x=1"]
    assert SETTINGS["mountaincar-3.0"].target_overrides("pilco", 0, None, [])[:4] == [
        "task=mountaincar", "task.env.power=3", "seed=0", "episodes=6"]


def test_a_run_s_figures_come_from_its_csv_rows():
    metrics = [{"return": str(r), "success": str(s), "source_samples": n, "relevance": w, "effective_samples": e}
               for r, s, n, w, e in [(1, 0, "", "", ""), (3, 1, "200", "0.5", "100"), (5, 1, "200", "nan", "")]]
    timings = [{"model_fit_s": f, "policy_search_s": p} for f, p in [("0", "0"), ("2", "10"), ("4", "20")]]
    r = run_result(7, [*metrics, metrics[-1]], timings, 3)
    assert (r["seed"], r["first_success"], r["auc"]) == (7, 1, 6.0)  # trapezoid: (1 + 3) / 2 + (3 + 5) / 2
    assert (r["model_fit_s_per_episode"], r["policy_search_s_per_episode"]) == (3.0, 15.0)  # the learned episodes
    assert r["relevance"] == [None, 0.5, None] and r["last_source_samples"] == 200 and r["last_relevance"] is None
    with pytest.raises(ValueError, match="3 needed"):
        run_result(7, metrics[:2], timings, 3)


def test_first_successes_pair_by_seed_and_never_counts_as_the_budget():
    arm = [fake(0, 1), fake(1, None), fake(2, 3), fake(4, 2)]
    baseline = [fake(0, 2), fake(1, 5), fake(2, 3), fake(3, 0)]
    pairs = first_success_pairs(arm, baseline, BUDGET)
    assert [(p["seed"], p["arm"], p["baseline"], p["verdict"]) for p in pairs["per_seed"]] == [
        (0, 1, 2, "earlier"), (1, BUDGET, 5, "later"), (2, 3, 3, "same")]
    assert (pairs["earlier"], pairs["same"], pairs["later"], pairs["paired"]) == (1, 1, 1, 3)


def test_goal_a_needs_four_of_five_paired_seeds_earlier():
    base = [fake(s, 4) for s in range(5)]
    four = [fake(0, 1), fake(1, 2), fake(2, 3), fake(3, None), fake(4, 0)]
    assert goal_a({"qtl_bayesian": base, "qtl_bayesian_samples": four}, BUDGET)["passed"] is True
    three = [*four[:3], fake(3, None), fake(4, 4)]
    assert goal_a({"qtl_bayesian": base, "qtl_bayesian_samples": three}, BUDGET)["passed"] is False
    assert goal_a({"qtl_bayesian": base, "qtl_bayesian_samples": four[:4]}, BUDGET)["passed"] is None  # partial


def test_goal_b_allows_five_percent_of_pilco_s_auc_per_seed():
    pilco = [fake(s, 1, 100.0) for s in range(5)]
    close = [fake(s, 1, 95.0) for s in range(5)]
    assert auc_pairs(close, pilco)["mean_difference"] == pytest.approx(-5.0)
    assert goal_b({"pilco": pilco, "samples": close, "qtl_bayesian_samples": pilco})["passed"] is True
    one_worse = [*close[:4], fake(4, 1, 94.0)]
    verdict = goal_b({"pilco": pilco, "samples": close, "qtl_bayesian_samples": one_worse})
    assert verdict["passed"] is False and verdict["not_worse"] == {"qtl_bayesian_samples": 4, "samples": 5}
    negative = [fake(s, 1, -100.0) for s in range(5)]  # |AUC|: a negative PILCO AUC still allows 5 % below it
    assert goal_b({"pilco": negative, "samples": [fake(s, 1, -105.0) for s in range(5)],
                   "qtl_bayesian_samples": negative})["passed"] is True
    assert goal_b({"pilco": pilco, "samples": close})["passed"] is None  # an arm not run


def test_the_section_marks_seeds_not_run():
    arms = {"pilco": [fake(s, 1) for s in range(5)], "samples": [fake(0, 1)]}
    info = {"machine": machine(), "episodes_per_run": BUDGET, "arms": arms, "seeds": [0, 1, 2, 3, 4],
            "goal": goal_b(arms), "command": "python scripts/bench_samples.py", "commit": "abc", "date": "today",
            "jobs": 1, "threads": 1, "sources": "runs/x/seed_<k>", "output": "docs/bench/samples-x.json",
            "comparisons": comparisons(arms, BUDGET)}
    text = "\n".join(section(SETTINGS["mountaincar-3.0"], info))
    assert "not judged: a partial run" in text
    assert "| 1 not run not run not run not run " in text
    assert "0/0 (5 not run)" in text
