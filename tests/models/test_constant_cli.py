"""An env with observation dimensions that never change, through the real CLI: the run completes and says so."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest
from gymnasium.utils.env_checker import check_env

from tests.constant_env import SENSOR_TASK, ConstantSensorEnv
from tests.helpers import CLI_TINY, PARTICLES_TINY

pytestmark = pytest.mark.e2e  # runs the real CLI in subprocesses: -m 'not e2e' skips it

ROOT = Path(__file__).resolve().parents[2]


def qtl(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = os.environ | {"PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    return subprocess.run([sys.executable, "-m", "qtl", *args], cwd=cwd, capture_output=True, text=True, timeout=300,
                          env=env)


def test_the_toy_env_is_a_valid_gymnasium_env():
    check_env(ConstantSensorEnv(), skip_render_check=True)


@pytest.mark.parametrize("budget", [CLI_TINY, PARTICLES_TINY], ids=["moment_matching", "particles"])
def test_a_run_on_an_env_with_constant_dimensions_completes_and_logs_the_detection(tmp_path, budget):
    # Its contact force (2) and target (3) never change: before, the first model fit failed with "noise_variance
    # [...] is below the floor"; now they are modelled as deterministic, and the GP learns p and v alone.
    (tmp_path / "my_configs" / "task").mkdir(parents=True)
    (tmp_path / "my_configs" / "task" / "sensor.yaml").write_text(SENSOR_TASK)
    tiny = [a for a in budget if not a.startswith("task.")]
    run_dir = tmp_path / "run"
    done = qtl("task=sensor", "hydra.searchpath=[file://my_configs]", *tiny, "progress=false",
               f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    log = (run_dir / "train.log").read_text()
    assert log.count("modelled as deterministic") == 1 and "outputs [2, 3]: Δ constant" in log
    with open(run_dir / "health.csv", newline="") as f:
        health = list(csv.DictReader(f))
    assert [int(r["constant_outputs"]) for r in health] == [0, 2]  # the random episode fits no model
    with open(run_dir / "metrics.csv", newline="") as f:
        learned = list(csv.DictReader(f))[1]
    assert learned["theta/out1/noise_variance"] and not learned["theta/out2/noise_variance"]


def test_a_run_on_it_transfers_to_a_target_that_also_models_them_as_deterministic(tmp_path):
    # θ_s holds the rows of p and v (its last fit's GP outputs); the target's model learns the same two.
    (tmp_path / "my_configs" / "task").mkdir(parents=True)
    (tmp_path / "my_configs" / "task" / "sensor.yaml").write_text(SENSOR_TASK)
    tiny = [a for a in CLI_TINY if not a.startswith("task.")]
    common = ["task=sensor", "hydra.searchpath=[file://my_configs]", *tiny, "progress=false"]
    source = qtl(*common, f"hydra.run.dir={tmp_path / 'source'}", cwd=tmp_path)
    assert source.returncode == 0, source.stderr
    target = qtl(*common, "+task.env.dt=0.25", f"transfer.source={tmp_path / 'source'}", "rule=bayesian",
                 f"hydra.run.dir={tmp_path / 'target'}", cwd=tmp_path)
    assert target.returncode == 0, target.stderr
    with open(tmp_path / "target" / "metrics.csv", newline="") as f:
        learned = list(csv.DictReader(f))[1]
    assert 0.0 <= float(learned["compliance"]) <= 1.0 and learned["theta/out0/noise_variance"]
