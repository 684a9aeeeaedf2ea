"""``scripts/research/relapse_starts.py`` on hand-made runs: episodes after the first success, by start state."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from qtl.checkpoint import save_checkpoint
from tests.report.fakes import write_run

pytestmark = pytest.mark.e2e  # runs the real script in a subprocess

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "research" / "relapse_starts.py"
ENV = {"id": "qtl/CartPoleSwingUp-v0", "pole_mass": 1.5}  # x_0 ~ N(0, 0.1² I), D = 4
TAIL = (3, 5)  # episodes whose start state lies at |z| = 3 (χ²_4 percentile 93.9 %); the others at |z| = 0.5 (0.7 %)


def _run(run_dir: Path, returns: list[float]) -> None:
    """A finished run (success: return >= 30) with its start states in its newest checkpoint."""
    write_run(run_dir, returns, env=ENV)
    states = [torch.tensor([[0.1 * (3.0 if e in TAIL else 0.5), 0.0, 0.0, 0.0]] * 3, dtype=torch.float64)
              for e in range(len(returns))]
    save_checkpoint(run_dir, len(returns) - 1, {"dataset": {"states": states}})


def _call(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=180,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})


def test_failures_by_percentile_and_shared_episodes(tmp_path: Path) -> None:
    _run(tmp_path / "target" / "pilco" / "m1.5" / "seed_0", [0, 36, 36, 20, 36, 20])  # first 1: T F T F after
    _run(tmp_path / "target" / "qtl_bayesian" / "m1.5" / "seed_0", [0, 0, 36, 20, 36, 36])  # first 2: F T T
    _run(tmp_path / "target" / "qtl_gamma_1" / "m1.5" / "seed_0", [0, 0, 0, 0, 0, 0])  # never: left out
    done = _call(str(tmp_path), "--output", str(tmp_path / "out.json"))
    assert done.returncode == 0, done.stderr[-3000:]
    numbers = json.loads((tmp_path / "out.json").read_text())
    assert len(numbers["episodes"]) == 7
    bins = {(b["low"], b["high"]): (b["episodes"], b["failures"]) for b in numbers["by_percentile"]}
    assert bins[(0.9, 1.0)] == (4, 3)  # episodes 3 and 5 of both runs; only QTL's episode 5 succeeds
    assert sum(n for n, _ in bins.values()) == 7 and sum(f for _, f in bins.values()) == 3
    low = next(b for b in numbers["by_percentile"] if b["high"] == 0.5)
    assert (low["episodes"], low["failures"]) == (3, 0)
    tail = next(e for e in numbers["episodes"] if e["episode"] == 3)
    assert tail["radius"] == pytest.approx(3.0) and tail["percentile"] == pytest.approx(1 - 5.5 * torch.e ** -4.5)
    shared = [(s["episode"], s["failed"], s["runs"]) for s in numbers["shared_failures"]]
    assert shared == [(3, 2, 2), (5, 1, 2)]  # most failures first; half of the runs counts
    assert "7 learned episodes after their run's first success, 3 failed (43%)." in done.stdout


def test_a_run_without_its_config_is_refused_in_one_line(tmp_path: Path) -> None:
    run = tmp_path / "target" / "pilco" / "m1.5" / "seed_0"
    _run(run, [0, 36, 20])
    (run / ".hydra" / "config.yaml").unlink()
    done = _call(str(tmp_path))
    assert done.returncode != 0
    assert done.stderr.strip().splitlines()[-1].endswith("run it with qtl-train, which writes the config it ran")
    assert _call(str(tmp_path / "nope")).stderr.strip().splitlines()[-1].endswith(
        "is not a directory: give an experiment directory")


def test_runs_without_their_checkpoints_are_refused_in_one_line(tmp_path: Path) -> None:
    run = tmp_path / "target" / "pilco" / "m1.5" / "seed_0"
    _run(run, [0, 36, 20])
    shutil.rmtree(run / "checkpoints")  # as a finished sweep kept in git holds it
    done = _call(str(tmp_path))
    assert done.returncode == 1 and "Traceback" not in done.stderr
    assert "1 of 1 run(s) hold no checkpoint" in done.stderr.strip().splitlines()[-1]
