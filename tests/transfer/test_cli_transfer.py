"""The transfer commands of docs/guide/transfer.md through the real CLI, and its bad-input messages, tiny budget."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import CLI_TINY

pytestmark = pytest.mark.e2e  # runs the real CLI in subprocesses: -m 'not e2e' skips it

TINY = [*CLI_TINY, "progress=false"]


def qtl(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "qtl", *TINY, *args], cwd=cwd, capture_output=True, text=True,
                          timeout=300)


@pytest.fixture(scope="module")
def source_dir(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("cli") / "source"
    done = qtl(f"hydra.run.dir={path}", cwd=path.parent)
    assert done.returncode == 0, done.stderr
    return path


def test_readme_transfer_command_runs_and_logs_compliance(source_dir, tmp_path):
    target = tmp_path / "target"
    done = qtl("task=cartpole", "task.env.pole_mass=2.0", f"transfer.source={source_dir}", "rule=bayesian",
               f"hydra.run.dir={target}", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    with open(target / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["kind"] for r in rows] == ["random", "policy"]  # rule=bayesian alone transfers θ_s, not ψ_s
    assert 0.0 <= float(rows[1]["compliance"]) <= 1.0
    assert "rule bayesian" in (target / "train.log").read_text()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["rule=forgetting", "rule.gamma=1.2"], "rule.gamma must be in [0, 1]"),
        (["rule=sometimes"], "rule/sometimes"),
        (["approach=qtl_bayesian", "task=mountaincar", "task.horizon=6"], "transfer only works within one family"),
        (["approach=qtl_bayesian", "task.angle_dims=[]"], "angle dimensions is [2] in the source run"),
    ],
)
def test_bad_transfer_input_fails_with_the_documented_message(source_dir, tmp_path, args, message):
    run_dir = tmp_path / "run"
    done = qtl(f"transfer.source={source_dir}", *args, f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert done.returncode != 0
    assert message in done.stderr
    assert not (run_dir / "metrics.csv").exists()
