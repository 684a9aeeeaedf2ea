"""``scripts/bench_compliance.py``: its Λ is the one the gate of a real target run reads at the first model."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import pytest

from qtl.loop import run
from qtl.metrics import Curve
from qtl.report import discover
from tests.helpers import TINY, tiny_config
from tests.report.fakes import table_rows
from tests.scripts.load import script

bench_compliance = script("bench_compliance")

SEED = 3


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> tuple[Path, Path, Path]:
    """A tiny 0.5 kg source run, and two tiny 2.0 kg θ-only transfer runs from it: ungated and gated at 1.0."""
    root = tmp_path_factory.mktemp("bench_compliance")
    sources = root / "sources"
    run(tiny_config("episodes=2", f"seed={SEED}"), sources / f"seed_{SEED}")
    transfer = [f"transfer.source={sources / f'seed_{SEED}'}", "approach=qtl_bayesian", "transfer.policy=false",
                "task.env.pole_mass=2.0", f"seed={SEED}", "episodes=2"]
    run(tiny_config(*transfer), root / "transfer")
    run(tiny_config(*transfer, "transfer.min_compliance=1.0"), root / "gated")
    run(tiny_config(*[o for o in transfer if o != "transfer.policy=false"]), root / "qtl")  # ψ_s transferred too
    return sources, root / "transfer", root / "gated"


def test_initial_compliance_is_what_the_run_logs_at_its_first_model(runs) -> None:
    sources, transfer, _ = runs
    family = dataclasses.replace(bench_compliance.FAMILIES["cartpole"], sources=sources)
    row = bench_compliance.initial_compliance(family, 2.0, SEED, list(TINY))
    logged = Curve.read(transfer).compliance
    assert row["kernel"] == pytest.approx(logged[1], rel=1e-9)  # episode 1: the first model, on episode 0's tuples
    assert 0.0 < row["kernel"] <= 1.0 and row["kernel"] >= row["kernel_no_bandwidth"]
    assert 0.0 <= row["likelihood_ratio"] <= 1.0
    assert row["tuples"] == 8 and row["seed"] == SEED and len(row["bandwidth"]) == 4
    by_psi_s = Curve.read(transfer.parent / "qtl").compliance  # a run that transfers ψ_s: its first episode is ψ_s's
    assert row["kernel_source_policy"] == pytest.approx(by_psi_s[1], rel=1e-9)
    assert row["kernel_source_policy"] != row["kernel"]


def test_the_gate_is_read_back_from_the_checkpoints(runs) -> None:
    _, transfer, gated = runs
    assert bench_compliance.fell_back_at(transfer) is None
    assert bench_compliance.fell_back_at(gated) == 1  # Λ < 1.0 at the first model: PILCO from episode 1 on


def test_verdict_orders_cart_pole_targets_by_mass() -> None:
    family = bench_compliance.FAMILIES["cartpole"]

    def rows(*values: float) -> dict[float, list[dict]]:
        return {v: [{"kernel": k}] for v, k in zip((*family.near, *family.far), values, strict=True)}

    assert all(bench_compliance.compliance_verdict(family, rows(0.9, 0.8, 0.6, 0.5, 0.3)).values())
    out_of_order = bench_compliance.compliance_verdict(family, rows(0.8, 0.9, 0.6, 0.5, 0.3))
    assert not out_of_order["ordered by mass"] and out_of_order["far target lowest"]
    saturated = bench_compliance.compliance_verdict(family, rows(0.99, 0.8, 0.6, 0.5, 0.3))
    assert not saturated["near targets not saturated (0.05 < Λ < 0.95)"]
    assert not bench_compliance.compliance_verdict(family, rows(0.9, 0.8, 0.6, 0.5, 0.55))["far target lowest"]


def test_learning_runs_pair_up_and_a_gate_at_the_first_model_is_pilco(runs, tmp_path) -> None:
    """--learn: every arm runs through the CLI; a run gated at its first model repeats PILCO's run exactly."""
    sources, _, _ = runs
    family = dataclasses.replace(bench_compliance.FAMILIES["cartpole"], sources=sources, near=(2.0,), far=())
    args = argparse.Namespace(runs_dir=tmp_path, approach="qtl_bayesian", gate=1.0, episodes=1, jobs=2, seeds=[SEED],
                              arms=list(bench_compliance.ARMS), overrides=list(TINY), figures=tmp_path / "results",
                              gate_on="all")
    args.figures.mkdir()
    results, table = bench_compliance.learn(family, args)
    arms = results["2.0"]
    assert set(arms) == {"pilco", "transfer", "qtl", "gated"}
    assert arms["gated"][0]["fell_back_after"] == 1 and arms["transfer"][0]["fell_back_after"] is None
    assert arms["gated"][0]["returns"] == arms["pilco"][0]["returns"]  # same seed, θ = θ_p from the first model
    assert arms["transfer"][0]["compliance"][1] == arms["gated"][0]["compliance"][1]  # the same tuples, one Λ
    assert arms["qtl"][0]["returns"][0] != arms["transfer"][0]["returns"][0]  # ψ_s runs the initial episode
    assert ("2.0 kg", "gated") in {row[:2] for row in table_rows(table)} and table.count("\n- 2.0 kg, ") == 4
    assert (tmp_path / "results" / "compliance_cartpole_learning_curves.png").stat().st_size > 0
    assert "](results/compliance_cartpole_learning_curves.png)" in table
    assert sorted(discover(tmp_path / "cartpole").approaches) == ["gated", "pilco", "qtl", "transfer"]


def test_exploration_runs_any_env_argument_through_the_cli(runs, tmp_path) -> None:
    """--explore: PILCO and θ-only transfer on a target set by an env argument the task config does not list."""
    sources, _, _ = runs
    family = dataclasses.replace(bench_compliance.FAMILIES["cartpole"], sources=sources)
    assert bench_compliance.env_override(family, "friction", 5.0) == "+task.env.friction=5"
    assert bench_compliance.env_override(family, "pole_mass", 2.0) == "task.env.pole_mass=2"
    args = argparse.Namespace(runs_dir=tmp_path, approach="qtl_bayesian", episodes=1, jobs=2, seeds=[SEED],
                              overrides=list(TINY), explore=[("friction", 5.0)], gate=1.0, explore_arms=None,
                              figures=tmp_path / "results")
    results, table = bench_compliance.explore(family, args)
    arms = results["friction=5"]
    assert set(arms) == {"pilco", "transfer", "gated"} and len(arms["pilco"][0]["returns"]) == 2
    assert arms["pilco"][0]["returns"] != arms["transfer"][0]["returns"]  # θ_s changed the first model
    assert arms["gated"][0]["returns"] == arms["pilco"][0]["returns"] and arms["gated"][0]["fell_back_after"] == 1
    run_dir = tmp_path / "cartpole" / "explore" / "pilco" / "friction5" / f"seed_{SEED}"
    assert "+task.env.friction=5" in (run_dir / ".hydra" / "overrides.yaml").read_text()
    assert ("friction = 5", "transfer") in {row[:2] for row in table_rows(table)}
    assert table.count("\n- friction=5, ") == 3
    assert (tmp_path / "results" / "compliance_cartpole_explore_learning_curves.png").stat().st_size > 0
    assert "](results/compliance_cartpole_explore_learning_curves.png)" in table


def test_exploration_runs_qtl_pilco_and_its_gate(runs, tmp_path) -> None:
    """--explore-arms qtl gated_qtl: θ_s and ψ_s (initial episode by ψ_s), and the same falling back at the gate."""
    sources, _, _ = runs
    family = dataclasses.replace(bench_compliance.FAMILIES["cartpole"], sources=sources)
    args = argparse.Namespace(runs_dir=tmp_path, approach="qtl_bayesian", episodes=1, jobs=2, seeds=[SEED],
                              overrides=list(TINY), explore=[("pole_mass", 2.0)], gate=1.0,
                              explore_arms=["qtl", "gated_qtl"], figures=tmp_path / "results")
    results, table = bench_compliance.explore(family, args)
    arms = results["pole_mass=2"]
    assert set(arms) == {"qtl", "gated_qtl"}
    assert arms["gated_qtl"][0]["returns"][0] == arms["qtl"][0]["returns"][0]  # both start with ψ_s's episode
    assert arms["gated_qtl"][0]["fell_back_after"] == 1 and arms["qtl"][0]["fell_back_after"] is None
    assert ("pole_mass = 2", "gated_qtl") in {row[:2] for row in table_rows(table)}
    assert "gated_qtl: qtl with `transfer.min_compliance=1.0`" in table


@pytest.mark.parametrize("item", ["friction", "friction=lots", "=5", "a b=1"])
def test_a_bad_exploration_target_is_named(item) -> None:
    with pytest.raises(ValueError, match=f"--explore takes KEY=VALUE.*got '{item}'"):
        bench_compliance.parse_targets([item])
