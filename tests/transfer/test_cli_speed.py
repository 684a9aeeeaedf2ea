"""A speed-integration run through the real CLI: its GP models the velocities only; it resumes and transfers."""

from __future__ import annotations

import csv
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from qtl.checkpoint import run_checkpoint
from tests.helpers import CLI_TINY

pytestmark = pytest.mark.e2e  # runs the real CLI in subprocesses: -m 'not e2e' skips it

TINY = [*CLI_TINY, "progress=false", "figure_every=0"]
SPEED = "propagation.integration=speed"


def qtl(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "qtl", *args], cwd=cwd, capture_output=True, text=True, timeout=300)


def rows(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def speed_source(tmp_path_factory) -> Path:
    """A cart-pole run with speed integration: one random and one learned episode."""
    path = tmp_path_factory.mktemp("speed") / "source"
    done = qtl(*TINY, SPEED, f"hydra.run.dir={path}", cwd=path.parent)
    assert done.returncode == 0, done.stderr
    return path


def test_the_gp_of_a_speed_run_models_and_records_the_velocities_only(speed_source):
    columns = rows(speed_source)[1].keys()
    assert "theta/out1/noise_variance" in columns and "theta_p/out3/signal_variance" in columns
    assert not any(c.startswith(("theta/out0/", "theta/out2/")) for c in columns)  # the positions: not fitted
    checkpoint = run_checkpoint(speed_source)
    assert checkpoint["theta"]["noise_variance"].shape == (2,)
    assert checkpoint["previous_fit"]["outputs"] == [1, 3]


def test_a_speed_run_resumes(speed_source, tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(speed_source, run_dir)
    done = qtl(f"resume={run_dir}", "episodes=2", "threads=1", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    resumed = rows(run_dir)
    assert [r["kind"] for r in resumed] == ["random", "policy", "policy"]
    assert float(resumed[2]["theta/out3/noise_variance"]) > 0


def test_a_speed_run_transfers_to_a_speed_target(speed_source, tmp_path):
    target = tmp_path / "target"
    done = qtl(*TINY, SPEED, "task.env.pole_mass=2.0", f"transfer.source={speed_source}", "rule=bayesian",
               f"hydra.run.dir={target}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    learned = rows(target)[1]
    assert 0.0 <= float(learned["compliance"]) <= 1.0
    source_theta = run_checkpoint(speed_source)["theta"]
    # θ_0 = θ_s (Eq. 6): the target's first model used the source's θ of the same two outputs.
    assert float(learned["theta/out1/noise_variance"]) == pytest.approx(float(source_theta["noise_variance"][0]))
    assert torch.is_tensor(source_theta["lengthscales"]) and source_theta["lengthscales"].shape[0] == 2


def test_a_delta_target_of_a_speed_source_is_refused_in_one_line_before_any_work(speed_source, tmp_path):
    target = tmp_path / "target"
    done = qtl(*TINY, "task.env.pole_mass=2.0", f"transfer.source={speed_source}", "rule=bayesian",
               f"hydra.run.dir={target}", cwd=tmp_path)
    assert done.returncode != 0
    assert "models outputs [1, 3] (integration=speed), this run models [0, 1, 2, 3]" in done.stderr
    assert "set propagation.integration=speed" in done.stderr and "Traceback" not in done.stderr
    assert not (target / "metrics.csv").exists()
