"""``scripts/bench_particle_step.py`` on a tiny finished recipe=mc_pilco run, as a subprocess."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from qtl.loop import run
from tests.helpers import TINY, train_config

pytestmark = pytest.mark.e2e  # runs the real script in a subprocess

ROOT = Path(__file__).resolve().parents[2]
ADAM_TINY = [o for o in TINY if not o.startswith("optimizer.")]


def bench(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "bench_particle_step.py"), *args],
                          capture_output=True, text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"},
                          cwd=ROOT)


def test_times_both_forward_forms_on_the_runs_data(tmp_path) -> None:
    run_dir = tmp_path / "run"
    run(train_config(*ADAM_TINY, "recipe=mc_pilco", "episodes=1", "optimizer.steps=4", "propagation.num_particles=16",
                     "policy.num_basis=12", "propagation.num_features=16"), run_dir)
    output = tmp_path / "step.json"
    done = bench(str(run_dir), "--repeats", "2", "--output", str(output), "--no-docs")
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(output.read_text())["results"][0]
    assert result["num_basis"] == 12 and result["particles"] == 16 and result["dropout"] == 0.25
    assert {"reference", "fused"} <= set(result["times_s"]) and all(len(t) == 2 for t in result["times_s"].values())
    assert result["ratios"]["fused"] == pytest.approx(result["median_s"]["fused"] / result["median_s"]["reference"])
    assert result["max_value_relative_difference"] <= 1e-6
    assert "fused" in done.stdout


def test_refuses_a_moment_matching_run_before_any_work(tmp_path) -> None:
    run_dir = tmp_path / "mm"
    run(train_config(*TINY, "episodes=1"), run_dir)
    done = bench(str(run_dir), "--no-docs", "--output", str(tmp_path / "x.json"))
    assert done.returncode != 0 and "not a particle run with policy=rbf_network" in done.stderr
    assert not (tmp_path / "x.json").exists()
