"""Tables S1-S3 on the synthetic cart-pole experiment (success: return >= 30, as the fakes write it)."""

from __future__ import annotations

import math

import pytest

from qtl.report.discover import discover
from qtl.report.successes import success_markdown, success_values
from tests.report.fakes import CARTPOLE, make_experiment, table_rows


@pytest.fixture(scope="module")
def experiment(tmp_path_factory: pytest.TempPathFactory):
    """The experiment of :data:`~tests.report.fakes.CARTPOLE`, discovered."""
    return discover(make_experiment(tmp_path_factory.mktemp("cartpole"), CARTPOLE))


def test_per_seed_values_are_hand_computed(experiment):
    values = success_values(experiment).set_index(["metric", "approach", "label", "seed"])["value"]
    # PILCO 1.5 kg, seed 1: [0, 36, 20, 36, 36, 36] succeeds at 1, fails at 2, ends with 3 successes.
    assert values[("first_success", "pilco", "m1.5", 1)] == 1
    assert values[("relapses", "pilco", "m1.5", 1)] == 1
    assert values[("final_successes", "pilco", "m1.5", 1)] == 3
    # QTL 2.0 kg, seed 0: [10, 20, ...] never succeeds: no first success, no relapses, 0 at the end.
    assert math.isnan(values[("first_success", "qtl_bayesian", "m2.0", 0)])
    assert math.isnan(values[("relapses", "qtl_bayesian", "m2.0", 0)])
    assert values[("final_successes", "qtl_bayesian", "m2.0", 0)] == 0
    # PILCO 2.0 kg, seed 1: cut to the cell's 6 episodes, so its successes at episodes 6-7 (return 100) do not count.
    assert math.isnan(values[("first_success", "pilco", "m2.0", 1)])
    assert values[("final_successes", "pilco", "m2.0", 1)] == 0


def test_markdown_cells(experiment):
    text = "\n\n".join(success_markdown(experiment))
    rows = table_rows(text)
    for row in [
        ("Approach", "m1.5", "m2.0", "Seeds"),
        ("PILCO (γ = 0)", "2.0 ± 1.4 (2/2)", "— (0/2)", "2"),  # S1: first successes 3 and 1; none at 2.0 kg
        ("QTL-PILCO Bayesian", "1.0 ± 0.0 (2/2)", "2.0 (1/2)", "2"),
        ("PILCO (γ = 0)", "0.5 ± 0.7", "—", "2"),  # S2: relapses 0 and 1; no seed to count at 2.0 kg
        ("QTL-PILCO Bayesian", "0.0 ± 0.0", "0.0", "2"),
        ("PILCO (γ = 0)", "3.0 ± 0.0", "0.0 ± 0.0", "2"),  # S3: 0 for every seed at 2.0 kg (NC)
        ("QTL-PILCO Bayesian", "3.0 ± 0.0", "1.5 ± 2.1", "2"),
    ]:
        assert row in rows, row
    positions = [text.index(f"**Table S{n}.**") for n in (1, 2, 3)]
    assert positions == sorted(positions)


def test_report_holds_the_tables_and_their_numbers(cartpole):
    _, text, tables = cartpole
    assert "## Successes (not in the paper)" in text and "**Table S3.**" in text
    s1 = tables["successes"]["first_success"]
    assert s1["pilco"]["m2.0"] == {"mean": None, "std": None, "n": 0, "seeds": 2,
                                   "per_seed": {"0": None, "1": None}}
    assert s1["qtl_bayesian"]["m2.0"]["per_seed"] == {"0": None, "1": 2.0}
    assert tables["successes"]["relapses"]["pilco"]["m1.5"]["mean"] == pytest.approx(0.5)
    assert tables["successes"]["final_successes"]["qtl_bayesian"]["m2.0"]["std"] == pytest.approx(math.sqrt(4.5))


def test_the_unconverged_runs_are_named_with_their_first_success(experiment, cartpole):
    # NC: no success among the last 3 of the cell's episodes. PILCO 2.0 kg: both seeds (seed 1's late successes
    # lie past the cut); QTL 2.0 kg: seed 0 only (seed 1 succeeds from episode 2 on).
    text = success_markdown(experiment)[-1]
    assert text == ("Runs with no success among the last 3 episodes (NC): 3: pilco/m2.0/seed_0 (never succeeded), "
                    "pilco/m2.0/seed_1 (never succeeded), qtl_bayesian/m2.0/seed_0 (never succeeded).")
    _, _, tables = cartpole
    assert tables["successes"]["unconverged"] == {"pilco/m2.0/seed_0": None, "pilco/m2.0/seed_1": None,
                                                  "qtl_bayesian/m2.0/seed_0": None}


def test_a_run_that_succeeded_and_lost_it_is_unconverged_with_its_first_success(tmp_path):
    runs = {"pilco": {"m1.0": {0: ([0, 30, 30, 10, 10, 10], [math.nan] * 6),  # succeeded at 1, lost it: NC
                               1: ([0, 10, 10, 10, 10, 30], [math.nan] * 6)}}}  # one success at the end: converged
    text = success_markdown(discover(make_experiment(tmp_path / "cartpole", runs)))[-1]
    assert text.endswith("(NC): 1: pilco/m1.0/seed_0 (first success at episode 1).")
