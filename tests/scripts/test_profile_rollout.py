"""``scripts/profile_rollout.py --experiment``: one search round of a full-scale preset, timed and profiled."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.report.fakes import table_rows

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "profile_rollout.py"
TINY = ["task.horizon=6", "task.success.last_steps=2", "task.policy_size=4", "optimizer.restarts=2",
        "model.restarts=1", "model.max_iter=3", "model.sparse_above=20", "model.inducing=8"]


@pytest.mark.e2e  # runs the script in a subprocess
def test_profiles_one_batched_round_of_the_presets_sparse_model() -> None:
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "--experiment", "cartpole_source", "--threads", "1", "--rows", "4", *TINY],
        capture_output=True, text=True, timeout=240, env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert done.returncode == 0, done.stderr[-3000:]
    # n = sparse_above + one horizon of the task's own transitions; R = the preset's restarts, batched
    assert "### experiment=cartpole_source: one search round, R = 2, H = 6, n = 26, sparse, m = 8" in done.stdout
    table = table_rows(done.stdout)
    assert table[0] == ("operation", "calls", "self CPU (ms)", "share")
    assert len(table) == 1 + 4  # --rows
    assert "Rollout + gradient: median" in done.stdout


def test_refuses_overrides_without_an_experiment() -> None:
    done = subprocess.run([sys.executable, str(SCRIPT), "task.horizon=6"], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2
    assert "need --experiment" in done.stderr.strip().splitlines()[-1]
