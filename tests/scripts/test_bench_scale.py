"""``scripts/bench_scale.py``: the runs of each preset's sweep, the episodes done, and a tiny real measurement."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.report.fakes import table_rows
from tests.scripts.load import script

bench_scale = script("bench_scale")

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "bench_scale.py"
TINY = ["task.horizon=6", "task.success.last_steps=2", "task.policy_size=4", "optimizer.max_iter=3",
        "optimizer.restarts=2", "model.restarts=1", "model.max_iter=3", "model.sparse_above=20", "model.inducing=8"]


def write_metrics(run_dir: Path, episodes: int) -> None:
    run_dir.mkdir(parents=True)
    rows = ["episode,kind,return", "0,random,0.0", *(f"{e},policy,1.0" for e in range(1, episodes + 1))]
    (run_dir / "metrics.csv").write_text("\n".join(rows) + "\n")


@pytest.mark.parametrize(("preset", "runs"), [("cartpole_source", 5), ("cartpole", 4 * 5 * 7),
                                               ("mountaincar", 3 * 5 * 2), ("aircraft", 5 * 2)])
def test_counts_the_runs_of_each_presets_sweep(preset: str, runs: int) -> None:
    assert bench_scale.sweep_runs(bench_scale.compose_stage(preset, [])) == runs


def test_counts_learned_episodes_capped_at_the_runs_length(tmp_path: Path) -> None:
    write_metrics(tmp_path / "target" / "pilco" / "m2.0" / "seed_0", 3)
    write_metrics(tmp_path / "target" / "qtl_bayesian" / "m2.0" / "seed_0", 9)  # a run longer than asked
    assert bench_scale.episodes_done(tmp_path / "target", episodes=5) == 3 + 5
    assert bench_scale.episodes_done(tmp_path / "source", episodes=5) == 0  # not started: no folder


@pytest.mark.e2e  # runs the script in a subprocess
def test_measures_each_task_once_and_bounds_what_remains(tmp_path: Path) -> None:
    docs = ROOT / "docs" / "benchmarks.md"
    before = docs.read_bytes()
    write_metrics(tmp_path / "cartpole" / "source" / "seed_0", 24)
    write_metrics(tmp_path / "cartpole" / "source" / "seed_1", 10)
    output = tmp_path / "scale.json"
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "--experiments", "cartpole", "--repeats", "1", "--experiments-root",
         str(tmp_path), "--output", str(output), "--no-docs", *TINY],
        capture_output=True, text=True, timeout=240, env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert docs.read_bytes() == before
    result = json.loads(output.read_text())
    [task] = result["tasks"]  # source and target fly the same task: measured once
    assert (task["task"], task["model"], task["inducing"], task["n"], task["restarts"]) == ("cartpole", "sparse", 8,
                                                                                            26, 2)
    assert task["fit_s"] > 0 and task["round_s"] > 0
    source, target = result["results"]
    assert (source["stage"], source["runs"], source["episodes"], source["episodes_done"]) == ("source", 5, 24, 34)
    assert (target["stage"], target["runs"], target["episodes_done"]) == ("target", 140, 0)
    for row in (source, target):
        assert row["search_bound_s"] == pytest.approx(3 * task["round_s"])
        assert row["sweep_bound_core_h"] == pytest.approx(row["runs"] * 24 * row["search_bound_s"] / 3600)
    assert source["remaining_bound_core_h"] == pytest.approx((5 * 24 - 34) * source["search_bound_s"] / 3600)
    assert ("cartpole", "target", "cartpole", "140", "24", "3") in {row[:6] for row in table_rows(done.stdout)}


def test_refuses_one_sweep_root_for_every_experiment(tmp_path: Path) -> None:
    done = subprocess.run([sys.executable, str(SCRIPT), "--no-docs", f"sweep.root={tmp_path}"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert "--experiments-root" in done.stderr.strip().splitlines()[-1]
    assert not any(tmp_path.iterdir())
