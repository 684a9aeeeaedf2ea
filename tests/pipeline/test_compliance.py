"""``qtl-compliance`` (:mod:`qtl.pipeline.compliance`) on tiny finished runs: Λ as the library computes it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from qtl.features import AngleFeatures
from qtl.loop import run
from qtl.pipeline import compliance
from qtl.transfer.compliance import kernel_compliance, task_compliance
from qtl.transfer.source import SourceRun
from tests.helpers import tiny_config
from tests.report.fakes import table_rows

ROOT = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> tuple[Path, Path]:
    """A finished 0.5 kg run and a finished 2.0 kg run, two learned episodes each."""
    source, target = tmp_path_factory.mktemp("source"), tmp_path_factory.mktemp("target")
    run(tiny_config("episodes=2", "seed=3"), source)
    run(tiny_config("episodes=2", "seed=4", "task.env.pole_mass=2.0"), target)
    return source, target


def command(*args: str) -> subprocess.CompletedProcess:
    done = subprocess.run([sys.executable, "-m", "qtl.pipeline.compliance", *args], capture_output=True, text=True,
                          timeout=300, env=ENV, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    return done


@pytest.mark.e2e  # the real command in a subprocess
@pytest.mark.parametrize("how", [[], ["--bandwidth", "none"], ["--compliance", "likelihood_ratio"]])
def test_compliance_equals_the_library_at_each_resolution(runs, tmp_path, how) -> None:
    source_dir, target_dir = runs
    output = tmp_path / "compliance.json"
    done = command(str(source_dir), str(target_dir), "--resolution", "0", "0.1", "--json", str(output), *how)
    header, printed = table_rows(done.stdout)
    assert header == ("target run", "n", "Λ, ρ = 0", "Λ, ρ = 0.1")
    row = json.loads(output.read_text())["targets"][0]
    assert printed == (row["target"], str(row["n"]), *(f"{row['compliance'][rho]:.2f}" for rho in ("0.0", "0.1")))
    source, target = SourceRun.load(source_dir), SourceRun.load(target_dir)
    features = AngleFeatures(source.task.state_dim, source.task.angle_dims)
    source_model, target_model = source.model(features), target.model(features)
    for rho in (0.0, 0.1):
        if "likelihood_ratio" in how:
            expected = task_compliance(source_model, target_model, resolution=rho).value
        else:
            bandwidth = "none" if "none" in how else "scott"
            expected = kernel_compliance(source_model, target_model, bandwidth=bandwidth, resolution=rho).value
        assert row["compliance"][str(rho)] == pytest.approx(expected, abs=1e-12)




def _refused(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """The last line ``qtl-compliance`` writes to stderr as it refuses ``argv`` (exit status 2, nothing run)."""
    with pytest.raises(SystemExit) as stop:
        compliance.main(argv)
    assert stop.value.code == 2
    return capsys.readouterr().err.strip().splitlines()[-1]


def test_bad_input_is_refused_in_one_line_before_any_work(tmp_path: Path, capsys) -> None:
    assert _refused([str(tmp_path), str(tmp_path / "nope")], capsys).endswith(
        "nope is not a directory: give finished runs' directories")
    assert "--temperature tempers the likelihood ratio only" in _refused(
        [str(tmp_path), str(tmp_path), "--temperature", "2"], capsys)
    empty = _refused([str(tmp_path), str(tmp_path)], capsys)  # a directory that is no run
    assert empty.startswith("qtl-compliance: error:") and str(tmp_path) in empty
