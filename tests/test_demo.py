"""``qtl-demo`` end to end on a tiny budget, and the reuse rules of ``qtl.launch``."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from qtl.errors import RunMismatch
from qtl.launch import ensure_run
from tests.helpers import BUDGET as TINY

pytestmark = pytest.mark.e2e  # runs the real CLI in subprocesses: -m 'not e2e' skips it


def test_demo_runs_source_transfer_and_baseline_then_summarises(tmp_path):
    exe = shutil.which("qtl-demo") or str(Path(__file__).resolve().parents[1] / ".venv" / "bin" / "qtl-demo")
    out = tmp_path / "demo"
    done = subprocess.run([exe, "--out", str(out), "--episodes", "1", *TINY], capture_output=True, text=True,
                          timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    for name in ("source", "target_qtl_bayesian", "target_pilco"):
        assert (out / name / "metrics.csv").is_file()
    table = [line for line in done.stdout.splitlines() if line.startswith("|") and not set(line) <= set("|:- ")]
    assert [line.split("|")[1].strip() for line in table] == [
        "run", "source 0.5 kg, PILCO", "target 2.0 kg, QTL Bayesian", "target 2.0 kg, PILCO"]
    # A repeated command reuses the finished runs instead of recomputing them.
    before = (out / "source" / "metrics.csv").stat().st_mtime_ns
    assert ensure_run(["seed=0", "episodes=1", *TINY], out / "source", 2) == 0.0
    assert (out / "source" / "metrics.csv").stat().st_mtime_ns == before
    with pytest.raises(RunMismatch, match="other overrides"):
        ensure_run(["seed=1", "episodes=1", *TINY], out / "source", 2)
    # A longer budget extends the run by resuming it (runs are causal: the same as a longer run).
    assert ensure_run(["seed=0", "episodes=2", *TINY], out / "source", 3) > 0
    assert len((out / "source" / "metrics.csv").read_text().splitlines()) == 1 + 3
