"""Smoke test of ``scripts/bench_policy_search.py``: its smallest configuration, writing nothing under docs/.

Two tests, which pytest-xdist can run side by side: the propagators (``--no-compare``), and the backend x
restarts comparison of issue 18 (``--compare-only``, a subset of its variants that takes every value of every switch),
both at n = 60.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.scripts.load import script

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "bench_policy_search.py"
TINY = [
    "--sizes", "60", "--dtypes", "float64", "--threads", "1", "--repeats", "1",
    "--overrides", "task.horizon=10", "task.success.last_steps=3",
    "--mm-overrides", "optimizer.max_iter=3", "optimizer.restarts=2",
    "--particles-overrides", "optimizer.steps=3", "propagation.num_particles=20",
    "--compare-sizes", "60",
]


def run_tiny(tmp_path: Path, *options: str) -> tuple[subprocess.CompletedProcess, dict]:
    """The smallest configuration with ``options``: the finished process and its JSON report; docs/ unchanged."""
    docs = ROOT / "docs" / "benchmarks.md"
    before = docs.read_bytes() if docs.exists() else None
    output = tmp_path / "policy_search.json"
    done = subprocess.run(
        [sys.executable, str(SCRIPT), *TINY, *options, "--output", str(output), "--cache-dir",
         str(tmp_path / "cache"), "--no-docs"],
        capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert (docs.read_bytes() if docs.exists() else None) == before
    assert list((tmp_path / "cache").glob("*.pt"))
    return done, json.loads(output.read_text())


def test_smallest_configuration_measures_both_propagators_without_touching_docs(tmp_path: Path) -> None:
    """Both propagators (particles: marginal, pathwise) timed at n = 60, no comparison; docs/ unchanged."""
    done, report = run_tiny(tmp_path, "--no-compare")
    assert [(r["propagator"], r["n"], r["dtype"]) for r in report["results"]] == [
        ("moment_matching", 60, "float64"), ("particles", 60, "float64"), ("particles_pathwise", 60, "float64")]
    for row in report["results"]:
        assert "error" not in row, row["error"]
        assert row["horizon"] == 10
        assert row["rollout_grad_s_median"] > 0 and row["search_s"] > 0 and row["peak_rss_mib"] > 0
        assert row["evaluations"] >= 3
        assert row["met"] == "—"  # no target at n = 60
    mm, particles, pathwise = report["results"]
    assert "variance_products_s_per_evaluation" not in mm
    assert particles["propagation"]["sampling"] == "marginal" and pathwise["propagation"]["sampling"] == "pathwise"
    assert pathwise["propagation"]["num_features"] == 256 and pathwise["optimizer"]["steps"] == 3
    assert pathwise["propagation"]["path_dtype"] == "float32"
    # Like with like: both particle rows run the mc_pilco recipe's propagation, apart from the sampling.
    for key in ("resample_every", "expected_reward", "include_noise", "num_particles", "reward_width_scale"):
        assert particles["propagation"][key] == pathwise["propagation"][key], key
    assert (pathwise["propagation"]["resample_every"], pathwise["propagation"]["expected_reward"]) == (1, False)
    assert particles["optimizer"] == pathwise["optimizer"]
    # Pathwise against marginal, in the same run: both times and their ratio in the section.
    ratio = pathwise["search_s"] / particles["search_s"]
    assert "Pathwise against marginal" in done.stdout
    assert f"policy search {pathwise['search_s']:.2f} s vs {particles['search_s']:.2f} s ({ratio:.2f}×" in done.stdout
    # The particles' floor: H products, each a part of what one rollout + gradient does.
    assert 0 < particles["variance_products_s_per_evaluation"] < particles["rollout_grad_s_median"]
    assert "arithmetic floor" in done.stdout and "s for 3 steps" in done.stdout
    assert not report["judged"]
    assert report["models"]["60"]["n"] == 60 and report["comparison"] == []
    assert "## Policy search" in done.stdout and "not measured here" in done.stdout
    assert "### Exp sums torch vs native" not in done.stdout


# Each value of each switch at least once (backend torch/native, restarts sequential/batched, moments
# reference/fused/native), with the baseline that always runs: 4 subprocesses instead of COMPARE_VARIANTS' 9.
VARIANTS = ["torch/batched/reference", "torch/sequential/fused", "native/batched/native"]


def test_smallest_comparison_times_the_chosen_variants_against_the_reference_path(tmp_path: Path) -> None:
    """``--compare-only --variants``: the baseline and the chosen rows at n = 60, each with its ratio."""
    done, report = run_tiny(tmp_path, "--compare-only", "--variants", *VARIANTS)
    assert report["results"] == [] and report["models"]["60"]["n"] == 60
    rows = {(r["backend"], r["batched"], r["moments"]): r for r in report["comparison"]}
    assert sorted(rows) == sorted([("torch", False, "reference"), ("torch", True, "reference"),
                                   ("torch", False, "fused"), ("native", True, "native")])
    for (backend, batched, moments), row in rows.items():
        if backend == "native" and "error" in row:  # the native kernel is optional: not built here
            assert "native" in row["error"]
            continue
        assert "error" not in row, row["error"]
        assert row["kernel_backend"] == backend and row["optimizer"]["batched"] is batched
        assert row["kernels"]["moments"] == moments
        assert row["search_s"] > 0 and len(row["run_values"]) == 2 and row["value_found"] == max(row["run_values"])
        # Batched: one rollout answers every restart still running (a stopped one leaves the batch).
        if batched:
            assert row["rollouts"] <= row["evaluations"] <= 2 * row["rollouts"]
        else:
            assert row["evaluations"] == row["rollouts"]
        assert ("batched_rollout_grad_s_median" in row) is batched
    base = rows[("torch", False, "reference")]
    assert base["search_s_ratio"] == 1.0
    batched = rows[("torch", True, "reference")]
    assert batched["search_s_ratio"] == batched["search_s"] / base["search_s"]
    # Same data, model and ψ_0 in every row: the same initial predicted return (the backends agree to round-off).
    for row in rows.values():
        if "value_initial" in row:
            assert row["value_initial"] == pytest.approx(base["value_initial"], rel=1e-9)
    assert "### Exp sums torch vs native, restarts sequential vs batched" in done.stdout


def test_an_unknown_variant_is_refused_in_one_line_before_any_measurement(tmp_path: Path) -> None:
    output = tmp_path / "policy_search.json"
    done = subprocess.run(
        [sys.executable, str(SCRIPT), *TINY, "--compare-only", "--variants", "native/batched/nope", "--output",
         str(output), "--cache-dir", str(tmp_path / "cache"), "--no-docs"],
        capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert done.returncode == 2
    assert "unknown --variants native/batched/nope: choose from torch/sequential/reference" in done.stderr
    assert not output.exists() and not (tmp_path / "cache").exists()


def test_smallest_integration_comparison_times_delta_and_speed_on_the_same_model(tmp_path: Path) -> None:
    """``--compare integration``: delta and speed searches at n = 60 and one aircraft round of each, ratios."""
    done, report = run_tiny(tmp_path, "--compare", "integration", "--aircraft-inducing", "20", "--aircraft-overrides",
                            "model.restarts=1", "model.max_iter=3", "task.horizon=10", "task.success.last_steps=3",
                            "optimizer.max_iter=2")
    rows = {r["integration"]: r for r in report["results"]}
    assert sorted(rows) == ["delta", "speed"]
    for integration, row in rows.items():
        assert "error" not in row, row["error"]
        assert row["propagation"]["integration"] == integration and row["n"] == 60
        assert row["search_s"] > 0 and row["rollout_grad_s_median"] > 0
    # The same data and ψ_0; the positions' model differs, and so does the predicted return.
    assert rows["delta"]["value_initial"] != rows["speed"]["value_initial"]
    aircraft = report["aircraft"]
    assert "error" not in aircraft, aircraft["error"]
    assert aircraft["model"] == "sparse" and aircraft["inducing"] == 20 and aircraft["state_dim"] == 12
    assert aircraft["kinematics"]["positions"] == [0, 1, 2, 3, 4, 5]
    assert aircraft["round_ratio"] == aircraft["delta"]["round_s"] / aircraft["speed"]["round_s"]
    assert "### Full-state vs kinematic moment matching" in done.stdout and "Aircraft (quadcopter" in done.stdout


def test_the_integration_comparison_names_its_files_by_device_and_tag() -> None:
    bench = script("bench_policy_search")
    assert bench.integration_suffix("cpu") == "_integration"
    assert bench.integration_suffix("cpu", "threads1") == "_integration-threads1"
