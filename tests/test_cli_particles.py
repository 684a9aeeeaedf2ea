"""``python -m qtl propagation=particles`` end to end on a tiny budget."""

from __future__ import annotations

import csv
import math
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import PARTICLES_TINY

pytestmark = pytest.mark.e2e  # runs the real CLI or scripts in subprocesses


def test_cli_trains_with_particle_rollouts(tmp_path: Path):
    run_dir = tmp_path / "run"
    done = subprocess.run(
        [sys.executable, "-m", "qtl", *PARTICLES_TINY, f"hydra.run.dir={run_dir}"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )
    assert done.returncode == 0, done.stderr
    config = (run_dir / ".hydra" / "config.yaml").read_text()
    assert "qtl.propagation.Particles" in config
    with open(run_dir / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["kind"] for r in rows] == ["random", "policy"]
    learned = rows[1]
    assert math.isfinite(float(learned["predicted_return"]))
    assert int(learned["policy_evaluations"]) == 3
    assert len(list((run_dir / "checkpoints").glob("episode_*.pt"))) == 2
