"""The research probes of ``scripts/research/`` on a tiny finished run, as subprocesses."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from qtl.loop import run
from tests.helpers import tiny_config

pytestmark = pytest.mark.e2e  # runs the real CLI or scripts in subprocesses

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> tuple[Path]:
    """A finished 0.5 kg run, two learned episodes."""
    source = tmp_path_factory.mktemp("source")
    run(tiny_config("episodes=2", "seed=3"), source)
    return (source,)


def script(name: str, *args: str) -> subprocess.CompletedProcess:
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "research" / name), *args], capture_output=True,
                          text=True, timeout=300, env=ENV, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    return done


def test_probe_reruns_the_last_search_with_other_settings(runs) -> None:
    (source_dir,) = runs
    done = script("probe_policy_search.py", str(source_dir), "--episodes", "1", "propagation=particles",
                  "propagation.num_particles=10", "optimizer=adam", "optimizer.steps=2")
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["episode"] == 2 and report["evaluations"] == 2
    assert report["overrides"][0] == "propagation=particles"
    assert len(report["real"]) == 1 and report["real"][0]["return"] >= 0


def test_value_probe_values_a_policy_by_every_propagator(runs) -> None:
    (source_dir,) = runs
    checkpoints = sorted((source_dir / "checkpoints").glob("episode_*.pt"))
    done = script("probe_policy_value.py", str(source_dir), "--data", str(checkpoints[1]), "--policy",
                  str(checkpoints[2]), "--draws", "2", "--particles", "20", "--features", "16")
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert (report["data_episode"], report["policy_episode"]) == (1, 2)
    # The cart-pole declares its kinematics: speed integration is valued too.
    assert set(report) >= {"moment_matching", "marginal", "pathwise", "marginal_speed", "pathwise_speed"}
    for name in ("marginal", "pathwise", "marginal_speed", "pathwise_speed"):
        assert len(report[name]) == 2 and all(0.0 <= v <= 8.0 for v in report[name])  # 8 steps of reward <= 1
        assert report[name][0] != report[name][1]  # two draws
    assert 0.0 <= report["moment_matching"] <= 8.0
    # The model fitted on checkpoint 1's data is the run's own model of episode 2 (warm-started as the run did),
    # so moment matching values episode 2's policy as the run's search did.
    with open(source_dir / "metrics.csv", newline="") as f:
        logged = float(list(csv.DictReader(f))[2]["predicted_return"])
    assert report["moment_matching"] == pytest.approx(logged, rel=1e-6)
    assert "configured" not in report  # the run's own propagator is moment matching
    particles = script("probe_policy_value.py", str(source_dir), "--data", str(checkpoints[1]), "--draws", "2",
                       "--particles", "20", "propagation=particles", "propagation.num_particles=20",
                       "propagation.reward_width_scale=4.0")
    report = json.loads(particles.stdout.strip().splitlines()[-1])
    assert len(report["configured"]) == 2 and len(report["configured_search_reward"]) == 2
    assert report["configured_search_reward"][0] > report["configured"][0]  # the 4× wider reward pays more


@pytest.mark.parametrize("approach", ["qtl_bayesian", "hyperparameters_transfer"])
def test_value_probe_searches_on_the_transfer_runs_own_model(runs, tmp_path, approach) -> None:
    """For a transfer run the probe's model is θ_i of the run's rule (Bayesian fusion's state from the checkpoint;
    the free rule's cold restarts from θ_s), not θ_p: moment matching repeats the run's logged prediction."""
    (source_dir,) = runs
    target = tmp_path / approach
    run(tiny_config("episodes=2", "seed=5", "task.env.pole_mass=2.0", f"approach={approach}",
                    f"transfer.source={source_dir}"), target)
    checkpoints = sorted((target / "checkpoints").glob("episode_*.pt"))
    done = script("probe_policy_value.py", str(target), "--data", str(checkpoints[1]), "--policy",
                  str(checkpoints[2]), "--draws", "1", "--particles", "10", "--features", "16")
    report = json.loads(done.stdout.strip().splitlines()[-1])
    with open(target / "metrics.csv", newline="") as f:
        logged = float(list(csv.DictReader(f))[2]["predicted_return"])
    assert report["moment_matching"] == pytest.approx(logged, rel=1e-6)


def test_kinematic_residual_measures_how_well_positions_follow_their_velocities(runs) -> None:
    (source_dir,) = runs
    rows = [line.split("|")[1:-1] for line in script("kinematic_residual.py", str(source_dir)).stdout.splitlines()
            if line.startswith("|") and not line.startswith("|:") and "position" not in line]
    assert [int(row[1]) for row in rows] == [0, 2]  # the cart-pole's x and θ
    for row in rows:  # the trapezoid rule at the env's dt: the residual is far below the moves it predicts
        median, largest, moves = float(row[5]), float(row[7]), float(row[8])
        assert median < 0.1 * moves and largest >= median
    coarse = [line for line in script("kinematic_residual.py", str(source_dir), "--weight", "0").stdout.splitlines()
              if line.startswith("|") and "0.1" in line.split("|")[4]]
    assert coarse and all(line.split("|")[5].strip() == "0" for line in coarse)  # explicit Euler, w = 0


def test_relevance_drift_judges_source_tuples_by_theta_s_the_last_model_and_the_target_alone(runs) -> None:
    (source_dir,) = runs
    done = script("relevance_drift.py", str(source_dir), str(source_dir), "--episodes", "1", "--refits", "2",
                  "--max-samples", "8")
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["source_tuples"] == 8 and report["target_tuples"] > 0
    assert [row["judged by"] for row in report["rows"]] == [
        "θ_s", "the last model, refit 1", "the last model, refit 2", "the judge: the target's tuples alone"]
    assert all(0 < w <= 1 for row in report["rows"] for key, w in row.items() if key.startswith("w, output"))
