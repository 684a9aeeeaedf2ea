"""The source-choice benchmark's logic: the nearest source, each arm's overrides, a run's figures and the table."""

from __future__ import annotations

import pytest

from qtl.bench.sources import (
    FAMILIES,
    arm_overrides,
    arms,
    goal_verdict,
    nearest,
    resume_command,
    section,
    seed_result,
    selection_verdict,
    single_arm,
)

CARTPOLE, MOUNTAINCAR = FAMILIES["cartpole"], FAMILIES["mountaincar"]


def test_the_nearest_source_is_nearest_by_ratio_not_by_difference():
    # 1.0 kg and 3.0 kg are both 1.0 kg from 2.0 kg; by ratio 3.0 kg (1.5) beats 1.0 kg (2.0).
    assert nearest(CARTPOLE.sources, CARTPOLE.target) == 3.0
    assert nearest(MOUNTAINCAR.sources, MOUNTAINCAR.target) == 1.0
    with pytest.raises(ValueError, match="equally near"):
        nearest((1.0, 4.0), 2.0)


def test_each_arm_runs_the_target_with_its_own_transfer():
    sources = ["lib/a", "lib/b", "lib/c"]
    runs = {arm: arm_overrides(MOUNTAINCAR, arm, 3, 6, sources, ["x=1"]) for arm in arms(MOUNTAINCAR)}
    common = ["task=mountaincar", "task.env.power=1.5", "seed=3", "episodes=6"]
    assert runs["compliance"] == [*common, "approach=qtl_bayesian", "transfer.source=[lib/a,lib/b,lib/c]",
                                  "transfer.select=compliance", "x=1"]
    assert runs["mixture"][-2] == "transfer.select=mixture"
    assert runs[single_arm(MOUNTAINCAR, 1.0)] == [*common, "approach=qtl_bayesian", "transfer.source=lib/b", "x=1"]
    assert runs["pilco"] == [*common, "x=1"]


def rows(returns, successes, selected=None, compliance=None):
    """Fake metrics.csv rows: the initial episode without a model, then learned ones."""
    out = []
    for i, (ret, ok) in enumerate(zip(returns, successes, strict=True)):
        row = {"episode": str(i), "return": str(ret), "success": str(ok)}
        if selected is not None:
            row["selected_source"] = "" if i == 0 else str(selected)
            for k, lam in enumerate(compliance):
                row[f"compliance/{k}"] = "" if i == 0 else str(lam)
        out.append(row)
    return out


def test_a_runs_choice_reads_as_the_library_value_and_its_figures_as_the_curves():
    result = seed_result(0, rows([0.0, 2.0, 4.0, 9.0], [0, 0, 1, 1], 2, [0.2, 0.5, 0.8]), 3, CARTPOLE.sources)
    assert result["selected_value"] == 3.0 and result["selection_constant"]
    assert result["compliance_first_model"] == [0.2, 0.5, 0.8]
    assert result["first_success"] == 2 and result["auc"] == pytest.approx(1.0 + 3.0)  # trapezoid, 3 episodes
    pilco = seed_result(1, rows([0.0, 1.0], [0, 0]), 2, CARTPOLE.sources)
    assert pilco["selected_value"] is None and pilco["first_success"] is None
    with pytest.raises(ValueError):
        seed_result(0, rows([0.0], [0]), 2, CARTPOLE.sources)


def fake_info(results, seeds):
    family = MOUNTAINCAR
    return {"machine": {"cpu": "cpu", "cores": 2, "torch": "t"}, "command": "python scripts/bench_sources.py",
            "commit": "abc", "date": "2026-12-06", "jobs": 1, "threads": 1, "overrides": [], "seeds": seeds,
            "episodes_per_run": 3, "output": "docs/bench/sources-mountaincar.json",
            "sources": {f"{v:g}": f"runs/s{v:g}" for v in family.sources}, "results": results,
            "selection": selection_verdict(family, results.get("compliance", []), seeds),
            "goal": goal_verdict(family, results, seeds), "unfinished": [], "resume": None}


def test_the_verdicts_and_the_table_mark_what_did_not_run():
    seeds = [0, 1, 2, 3, 4]
    results = {arm: [] for arm in arms(MOUNTAINCAR)}
    for seed in seeds:
        chosen = 0 if seed == 4 else 1  # the nearest, 100 %, in 4 of 5 seeds
        results["compliance"].append(seed_result(seed, rows([0, 5, 5], [0, 1, 1], chosen, [0.3, 0.9, 0.1]), 3,
                                                 MOUNTAINCAR.sources))
        for value, ret in zip(MOUNTAINCAR.sources, (1, 4, 7), strict=True):
            results[single_arm(MOUNTAINCAR, value)].append(
                seed_result(seed, rows([0, ret, ret], [0, 0, 1]), 3, MOUNTAINCAR.sources))
    info = fake_info(results, seeds)
    assert info["selection"]["passed"] and info["selection"]["picked_nearest"] == 4
    # AUC: compliance 2.5 + 5 = 7.5; the single sources 1.5, 6 and 10.5, mean 6 (the mixture and PILCO not needed)
    assert info["goal"] == {"compliance_mean_auc": 7.5, "single_source_mean_auc": 6.0, "passed": True}
    lines = "\n".join(section(MOUNTAINCAR, info)).splitlines()
    choices = [line.replace(" ", "") for line in lines if line.startswith("|")][2:7]
    assert choices[0] == "|0|0.30|0.90|0.10|100%|yes|notrun|" and choices[4].endswith("|50%|no|notrun|")
    mixture = next(line for line in lines if line.startswith("| select=mixture"))
    assert "not run not run not run not run not run" in mixture and "0/5 (not run: 0 1 2 3 4)" in mixture
    text = "\n".join(lines)
    assert "**Required: select=compliance picks the nearest source in at least 4 of 5 seeds — met" in text


def test_a_partial_run_is_not_judged():
    results = {"compliance": [seed_result(0, rows([0, 1], [0, 0], 1, [0.1, 0.9, 0.2]), 2, MOUNTAINCAR.sources)]}
    verdict = selection_verdict(MOUNTAINCAR, results["compliance"], [0, 1, 2, 3, 4])
    assert verdict["passed"] is None and verdict["picked_nearest"] == 1


def test_the_resume_command_runs_every_arm():
    command = "python scripts/bench_sources.py --families cartpole --arms compliance 0.5 --jobs 1 --no-run x=1"
    assert resume_command(command) == "python scripts/bench_sources.py --families cartpole --jobs 1 x=1"
