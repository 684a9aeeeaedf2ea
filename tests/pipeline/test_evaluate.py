"""``qtl-evaluate`` (:mod:`qtl.pipeline.evaluate`) on a real (tiny) run: its final policy replayed from given starts."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from qtl.loop import run
from qtl.report import write_report
from qtl.report.final_policies import FINAL_POLICIES_FILE
from tests.helpers import tiny_config
from tests.test_runs import BEFORE_THE_FAST_PATHS, as_made_before_the_fast_paths

pytestmark = pytest.mark.e2e  # runs the real command in a subprocess

SEED = 3


def _call(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "qtl.pipeline.evaluate", *args], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})


@pytest.fixture(scope="module")
def experiment(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An experiment directory with one finished target run: 1 random + 1 learned episode."""
    root = tmp_path_factory.mktemp("exp")
    run(tiny_config("episodes=1", f"seed={SEED}"), root / "target" / "pilco" / "m0.5" / f"seed_{SEED}")
    return root


def test_replays_the_last_episode_from_its_own_start(experiment: Path, tmp_path: Path) -> None:
    # With the run's own seed as --eval-seed, start 1 is the start state of the run's episode 1, which the
    # checkpointed (final) policy ran: the replay must give that episode's return and success exactly.
    output = tmp_path / "eval.json"
    done = _call(str(experiment), "--starts", "3", "--eval-seed", str(SEED), "--output", str(output))
    assert done.returncode == 0, done.stderr[-3000:]
    (evaluation,) = json.loads(output.read_text())["runs"]
    with open(experiment / "target" / "pilco" / "m0.5" / f"seed_{SEED}" / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert (evaluation["approach"], evaluation["label"], evaluation["seed"]) == ("pilco", "m0.5", SEED)
    assert evaluation["episode"] == len(rows) - 1 == 1
    assert evaluation["returns"][1] == pytest.approx(float(rows[1]["return"]), rel=1e-12)
    assert len(set(evaluation["returns"])) == 3  # three different start states
    assert 0.0 <= evaluation["success_rate"] <= 1.0
    assert "PILCO (γ = 0)" in done.stdout
    assert "**Table F1.** Final policies: the share of the 3 start states" in done.stdout
    assert f"Written to {output}." in done.stdout


def test_the_default_starts_are_reproducible_and_not_the_runs_own(experiment: Path, tmp_path: Path) -> None:
    first = _call(str(experiment), "--starts", "2")  # by default into the experiment, where the report reads it
    second = _call(str(experiment), "--starts", "2", "--output", str(tmp_path / "2.json"))
    assert first.returncode == 0 and second.returncode == 0, first.stderr[-3000:]
    runs = [json.loads(path.read_text())["runs"][0]["returns"]
            for path in (experiment / FINAL_POLICIES_FILE, tmp_path / "2.json")]
    assert runs[0] == runs[1]
    report = write_report(experiment, tmp_path / "report").read_text()
    assert "**Table F1.** Final policies: the share of the 2 start states" in report
    assert "not evaluated" not in report
    own = _call(str(experiment), "--starts", "2", "--eval-seed", str(SEED), "--output", str(tmp_path / "own.json"))
    assert own.returncode == 0, own.stderr[-3000:]
    assert json.loads((tmp_path / "own.json").read_text())["runs"][0]["returns"] != runs[0]  # other start states


def test_bad_arguments_are_refused_in_one_line(tmp_path: Path) -> None:
    assert _call(str(tmp_path / "nope")).stderr.strip().splitlines()[-1].endswith(
        "is not a directory: give an experiment directory")
    assert _call(str(tmp_path), "--starts", "0").stderr.strip().splitlines()[-1].endswith(
        "give at least one start state")
    empty = _call(str(tmp_path))  # a directory without runs: named in one line, nothing written
    assert empty.returncode == 2 and "Traceback" not in empty.stderr and str(tmp_path) in empty.stderr
    assert not (tmp_path / "final_policies.json").exists()


def test_runs_without_their_checkpoints_are_refused_in_one_line_before_any_work(experiment: Path,
                                                                                tmp_path: Path) -> None:
    # A finished sweep kept in git holds no checkpoints (docs/experiments/README.md): the command names what is missing.
    lean = tmp_path / "lean"
    shutil.copytree(experiment, lean, ignore=shutil.ignore_patterns("checkpoints", FINAL_POLICIES_FILE))
    done = _call(str(lean), "--starts", "2")
    assert done.returncode == 2 and "Traceback" not in done.stderr
    last = done.stderr.strip().splitlines()[-1]
    assert f"1 of 1 run(s) hold no checkpoint (checkpoints/episode_NNNN.pt), whose policy this command runs: " \
           f"target/pilco/m0.5/seed_{SEED};" in last
    assert not (lean / FINAL_POLICIES_FILE).exists()


def test_a_run_made_before_the_fast_paths_is_replayed_as_it_ran(tmp_path: Path) -> None:
    # Its stored config lacks the keys issue 18 added (the engine, model.warm_start, optimizer.batched): the run is
    # rebuilt with the values it ran with (qtl.runs.load_run migrates the config as resume does), not with today's
    # defaults, and its last episode replays exactly.
    run_dir = tmp_path / "target" / "pilco" / "m0.5" / f"seed_{SEED}"
    run(tiny_config("episodes=1", f"seed={SEED}", *BEFORE_THE_FAST_PATHS), run_dir)
    as_made_before_the_fast_paths(run_dir)
    output = tmp_path / "eval.json"
    done = _call(str(tmp_path), "--starts", "2", "--eval-seed", str(SEED), "--output", str(output))
    assert done.returncode == 0, done.stderr[-3000:]
    (evaluation,) = json.loads(output.read_text())["runs"]
    with open(run_dir / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert evaluation["returns"][1] == pytest.approx(float(rows[1]["return"]), rel=1e-12)
