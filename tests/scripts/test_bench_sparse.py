"""Smoke test of ``scripts/bench_sparse.py``: exact below the threshold, sparse above, docs/ untouched."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import BUDGET

pytestmark = pytest.mark.e2e  # runs the real CLI or scripts in subprocesses

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "scripts" / "bench_sparse.py"


def test_switches_to_the_sparse_gp_above_the_threshold(tmp_path: Path) -> None:
    docs = ROOT / "docs" / "benchmarks.md"
    before = docs.read_bytes()
    output = tmp_path / "sparse.json"
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "--sizes", "40", "80", "--threads", "1", "--repeats", "1", "--overrides",
         "model.sparse_above=50", "model.inducing=20", *BUDGET,
         "--output", str(output), "--no-docs"],
        capture_output=True, text=True, timeout=240, env={**os.environ, "OMP_NUM_THREADS": "1"},
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert docs.read_bytes() == before
    rows = json.loads(output.read_text())["results"]
    assert [(r["n"], r["model"], r["inducing"]) for r in rows] == [(40, "exact", None), (80, "sparse", 20)]
    assert all(r["fit_s"] > 0 and r["rollout_grad_s_median"] > 0 and r["horizon"] == 6 for r in rows)
