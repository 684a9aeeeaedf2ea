"""The scripts of ``examples/`` run as a user runs them (a subprocess, from another directory), on a tiny budget."""

from __future__ import annotations

import csv
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from matplotlib import image
from omegaconf import OmegaConf

from qtl.checkpoint import latest_checkpoint, load_checkpoint
from tests.helpers import BUDGET

pytestmark = pytest.mark.e2e  # each runs a script in a subprocess: -m 'not e2e' skips them

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
NUMBER = r"(-?\d+\.\d+|nan|-?inf)"


def run_example(script: str, *args: str, cwd: Path) -> str:
    """Run ``examples/<script>`` with ``args`` in ``cwd`` on one torch thread; its stdout (a failure shows stderr)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, str(EXAMPLES / script), *args], capture_output=True, text=True,
                          timeout=300, cwd=cwd, env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def metrics(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_quickstart_learns_with_the_library_and_prints_finite_returns(tmp_path):
    out = run_example("quickstart.py", "episodes=2", *BUDGET, cwd=tmp_path)
    lines = out.splitlines()
    assert re.fullmatch(rf"episode 0 \(random actions\): return {NUMBER}", lines[0]), out
    learned = [re.fullmatch(rf"episode (\d): return {NUMBER}, success (True|False)", line) for line in lines[1:]]
    assert all(learned) and [m[1] for m in learned] == ["1", "2"], out
    returns = [float(re.search(NUMBER, lines[0].split("return")[1])[0])] + [float(m[2]) for m in learned]
    assert all(math.isfinite(r) and 0.0 <= r <= 6.0 for r in returns)  # at most 1 per step, 6 steps
    assert list(tmp_path.iterdir()) == []  # it writes nothing


def test_cartpole_transfer_runs_source_and_both_targets_and_plots_the_targets(tmp_path):
    out_dir = tmp_path / "transfer"
    out = run_example("cartpole_transfer.py", "--episodes", "1", "--tiny", "--seed", "2", "--out", str(out_dir),
                      "threads=1", cwd=tmp_path)
    runs = {name: metrics(out_dir / name) for name in ("source", "target_qtl_bayesian", "target_pilco")}
    assert all(len(rows) == 2 for rows in runs.values())  # 1 initial + 1 learned episode each
    assert all(math.isfinite(float(r["return"])) for rows in runs.values() for r in rows)
    # QTL starts from ψ_s and θ_s (its compliance is measured); PILCO from random actions; the target is 2.0 kg.
    assert [r["kind"] for r in runs["target_qtl_bayesian"]] == ["source_policy", "policy"]
    assert [r["kind"] for r in runs["target_pilco"]] == ["random", "policy"]
    assert 0.0 < float(runs["target_qtl_bayesian"][1]["compliance"]) <= 1.0
    masses = {name: OmegaConf.create(load_checkpoint(latest_checkpoint(out_dir / name))["config"]).task.env.pole_mass
              for name in runs}
    assert masses == {"source": 0.5, "target_qtl_bayesian": 2.0, "target_pilco": 2.0}
    # One PNG with both target curves: a valid image, each curve's colour drawn in it.
    figure = out_dir / "target_learning_curves.png"
    assert f"learning curves: {figure}" in out
    pixels = image.imread(figure)
    assert pixels.shape == (400, 700, 4)
    for colour in ((0xD6, 0x27, 0x28), (0x1F, 0x77, 0xB4)):  # QTL's red, PILCO's blue
        assert (np.abs(pixels[..., :3] * 255 - colour).max(-1) < 2).sum() > 100, colour
    rows = [line for line in out.splitlines() if line.startswith("|") and not set(line) <= set("|:- ")]
    table = [line.split("|")[1].strip() for line in rows]
    assert table == ["run", "source 0.5 kg, PILCO", "target 2.0 kg, QTL-PILCO, Bayesian (θ_s, ψ_s)",
                     "target 2.0 kg, PILCO from scratch"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["transfer"]  # everything under --out


def test_byo_env_registers_its_env_learns_it_and_reuses_the_finished_run(tmp_path):
    run_dir = tmp_path / "byo"
    out = run_example("byo_env.py", "--episodes", "2", "--tiny", "--out", str(run_dir), cwd=tmp_path)
    rows = metrics(run_dir)
    assert [r["kind"] for r in rows] == ["random", "policy", "policy"]
    assert all(float(r["env_return"]) < 0 <= float(r["return"]) for r in rows)  # its own cost beside qtl's reward
    printed = [re.fullmatch(rf"\s*(\d)\s+{NUMBER}\s+(yes|no)", line) for line in out.splitlines()]
    printed = [m for m in printed if m]
    assert [int(m[1]) for m in printed] == [0, 1, 2]
    assert [float(m[2]) for m in printed] == pytest.approx([float(r["return"]) for r in rows], abs=0.005)
    assert all(math.isfinite(float(m[2])) for m in printed)
    # Run again: the finished run is reused (no episode run again, no checkpoint written), not refused or redone.
    checkpoints = {p.name: p.stat().st_mtime_ns for p in (run_dir / "checkpoints").iterdir()}
    again = run_example("byo_env.py", "--episodes", "2", "--tiny", "--out", str(run_dir), cwd=tmp_path)
    assert again.splitlines()[-5:] == out.splitlines()[-5:]
    assert {p.name: p.stat().st_mtime_ns for p in (run_dir / "checkpoints").iterdir()} == checkpoints
    assert len(metrics(run_dir)) == 3


def test_the_readmes_python_example_is_the_quickstart_script():
    """README.md's "From Python" block is examples/quickstart.py's code, so the tested script is what users copy."""
    root = Path(__file__).resolve().parents[2]
    readme = (root / "README.md").read_text()
    block = readme.split("## From Python", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    script = (root / "examples" / "quickstart.py").read_text().split('"""', 2)[2]
    assert block.strip() == script.strip()
