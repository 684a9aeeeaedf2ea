"""Smoke test of ``scripts/bench_sparse_bound.py``: both evidence paths timed and compared, a fit each."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.e2e  # runs the real script in a subprocess

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "bench_sparse_bound.py"


def test_times_both_paths_and_fits_with_each(tmp_path: Path) -> None:
    docs = ROOT / "docs" / "benchmarks.md"
    before = docs.read_bytes()
    output = tmp_path / "sparse_bound.json"
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "--sizes", "60", "--inducing", "15", "--fit", "synthetic-60", "--checkpoint",
         "none", "--repeats", "1", "--output", str(output), "--no-docs"],
        capture_output=True, text=True, timeout=240, env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert docs.read_bytes() == before
    (row,) = json.loads(output.read_text())["results"]
    assert (row["case"], row["n"], row["inducing"], row["outputs"]) == ("synthetic-60", 60, 15, 4)
    assert row["gpytorch_s"] > 0 and row["closed_form_s"] > 0
    assert row["value_rel_diff"] < 1e-10 and row["grad_rel_diff"] < 1e-6
    fits = row["fit_gpytorch"], row["fit_closed_form"]
    assert all(fit["evaluations"] > 1 for fit in fits)
    assert abs(fits[0]["objective"] - fits[1]["objective"]) < 1e-4


def test_a_missing_checkpoint_is_refused_in_one_line(tmp_path: Path) -> None:
    done = subprocess.run([sys.executable, str(SCRIPT), "--checkpoint", str(tmp_path / "nope.pt"), "--no-docs"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "nope.pt does not exist" in done.stderr
