"""Tables F1-F2: ``final_policies.json`` read back per cell, stale evaluations named, hand-computed cells."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from qtl.report import discover, write_report
from qtl.report.final_policies import FINAL_POLICIES_FILE, SOURCE, final_policies_json, read_final_policies
from tests.report.fakes import CARTPOLE, make_experiment

STARTS, EVAL_SEED = 4, 11


def evaluation(approach: str, label: str, seed: int, episode: int, rate: float, mean: float) -> dict:
    return {"approach": approach, "label": label, "seed": seed, "episode": episode, "success_rate": rate,
            "mean_return": mean, "returns": [mean] * STARTS}


def write_evaluations(root: Path, runs: list[dict]) -> None:
    (root / FINAL_POLICIES_FILE).write_text(json.dumps({"starts": STARTS, "eval_seed": EVAL_SEED, "runs": runs}))


@pytest.fixture
def root(tmp_path: Path) -> Path:
    """The synthetic cart-pole experiment, its final policies evaluated: every run at its last episode but two."""
    root = make_experiment(tmp_path / "cartpole", CARTPOLE)
    write_evaluations(root, [
        evaluation(SOURCE, SOURCE, 0, 3, 1.0, 40.0), evaluation(SOURCE, SOURCE, 1, 3, 0.5, 30.0),
        evaluation("pilco", "m2.0", 0, 5, 0.25, 20.0),
        evaluation("pilco", "m2.0", 1, 7, 0.75, 30.0),  # 8 episodes: its last is 7, though the cell uses 6
        evaluation("pilco", "m1.5", 0, 5, 1.0, 36.0),
        evaluation("pilco", "m1.5", 1, 4, 1.0, 36.0),  # stale: the run went on to episode 5 since
        evaluation("qtl_bayesian", "m1.5", 0, 5, 0.5, 35.0), evaluation("qtl_bayesian", "m1.5", 1, 5, 1.0, 37.0),
        evaluation("qtl_bayesian", "m2.0", 0, 5, 0.0, 10.0),  # seed 1 never evaluated
        evaluation("policy_transfer", "m2.0", 0, 5, 1.0, 40.0),  # a run the experiment does not hold
    ])
    return root


def test_only_evaluations_of_each_runs_last_episode_count(root: Path) -> None:
    found = read_final_policies(discover(root))
    assert (found.starts, found.eval_seed) == (STARTS, EVAL_SEED)
    assert found.stale == ["pilco/m1.5/seed_1", "qtl_bayesian/m2.0/seed_1"]
    rates = found.values[found.values["metric"] == "success_rate"].set_index(["approach", "label", "seed"])["value"]
    assert rates.to_dict() == {("qtl_bayesian", "m1.5", 0): 0.5, ("qtl_bayesian", "m1.5", 1): 1.0,
                               ("qtl_bayesian", "m2.0", 0): 0.0, ("pilco", "m2.0", 0): 0.25,
                               ("pilco", "m2.0", 1): 0.75, ("pilco", "m1.5", 0): 1.0}
    assert sorted(found.sources["value"]) == [0.5, 1.0, 30.0, 40.0]


def test_json_cells_are_mean_std_over_the_evaluated_seeds(root: Path) -> None:
    found = read_final_policies(discover(root))
    assert found is not None
    numbers = final_policies_json(found)
    assert numbers["starts"] == STARTS and numbers["stale"] == ["pilco/m1.5/seed_1", "qtl_bayesian/m2.0/seed_1"]
    pilco = numbers["success_rate"]["pilco"]["m2.0"]
    assert pilco["mean"] == pytest.approx(0.5) and pilco["std"] == pytest.approx(0.5 ** 0.5 / 2) and pilco["n"] == 2
    assert pilco["per_seed"] == {"0": 0.25, "1": 0.75}
    assert numbers["mean_return"]["pilco"]["m1.5"] == {"mean": 36.0, "std": None, "n": 1, "per_seed": {"0": 36.0}}
    assert numbers["source_mean_return"]["mean"] == pytest.approx(35.0) and numbers["source_mean_return"]["n"] == 2


def test_report_holds_tables_f1_f2_and_names_the_stale_runs(root: Path) -> None:
    report = write_report(root).read_text()
    section = report.split("## Final policies (not in the paper)")[1].split("\n## ")[0]
    assert f"same {STARTS} start states (drawn with seed {EVAL_SEED}" in section
    assert f"qtl-evaluate {root} --finished-only" in section
    f1, f2 = section.split("**Table F1.**")[1].split("**Table F2.**")
    # Columns m1.5, m2.0; seeds evaluated per cell. PILCO m1.5: seed 0's 100 % (seed 1 stale); m2.0: 25 and
    # 75 % -> 50 ± 35 %. QTL Bayesian m1.5: 50 and 100 % -> 75 ± 35 %; m2.0: seed 0's 0 % (seed 1 not evaluated).
    assert "| PILCO (γ = 0)      |     100 | 50 ± 35 |    1, 2 |" in f1
    assert "| QTL-PILCO Bayesian | 75 ± 35 |       0 |    2, 1 |" in f1
    assert "36.00" in f2 and "25.00 ± 7.07" in f2
    assert "Sources (2 seeds): success 75 ± 35 %, total reward 35.00 ± 7.07." in section
    assert "(2 run(s); rerun the command above): pilco/m1.5/seed_1, qtl_bayesian/m2.0/seed_1." in section
    tables = json.loads((root / "report" / "tables.json").read_text())
    assert tables["final_policies"]["success_rate"]["pilco"]["m2.0"]["n"] == 2


def test_without_evaluations_the_report_has_no_such_section(tmp_path: Path) -> None:
    root = make_experiment(tmp_path / "cartpole", CARTPOLE)
    report = write_report(root).read_text()
    assert "Final policies" not in report
    assert json.loads((root / "report" / "tables.json").read_text())["final_policies"] is None


@pytest.mark.parametrize("text", ["{not json", '{"starts": 4, "eval_seed": 1}',
                                  '{"starts": 4, "eval_seed": 1, "runs": [{}]}',
                                  '{"starts": 4, "eval_seed": 1, "runs": [{"approach": "pilco", "label": "m1.5", '
                                  '"seed": 0, "episode": 5, "success_rate": 1.0}]}'])
def test_a_file_that_is_not_the_commands_output_is_refused_in_one_line(tmp_path: Path, text: str) -> None:
    root = make_experiment(tmp_path / "cartpole", CARTPOLE)
    (root / FINAL_POLICIES_FILE).write_text(text)
    with pytest.raises(ValueError, match=r"final_policies.json is not what qtl-evaluate writes .*"
                                         r"rerun `qtl-evaluate .* --finished-only`") as err:
        write_report(root)
    assert "\n" not in str(err.value)
