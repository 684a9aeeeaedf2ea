"""Recorded paths: relative to the repository holding them, never a machine's absolute path where avoidable."""

from __future__ import annotations

from pathlib import Path

from qtl.report import write_report
from qtl.report.paths import recorded_override, recorded_path, repository_root
from tests.report.fakes import CARTPOLE, make_experiment

REPO = Path(__file__).resolve().parents[2]


def test_a_path_in_a_repository_is_recorded_relative_to_its_top(tmp_path, monkeypatch):
    (tmp_path / "clone" / ".git").mkdir(parents=True)
    (tmp_path / "worktree").mkdir()
    (tmp_path / "worktree" / ".git").write_text("gitdir: elsewhere\n")  # a worktree's .git is a file
    monkeypatch.chdir(tmp_path / "worktree")
    assert repository_root(tmp_path / "clone" / "docs" / "x") == tmp_path / "clone"
    assert recorded_path(tmp_path / "clone" / "docs" / "experiments" / "cartpole") == "docs/experiments/cartpole"
    assert recorded_path(tmp_path / "clone") == "."
    assert recorded_path("runs/cartpole") == "runs/cartpole"  # relative to the current directory's repository
    assert recorded_path(REPO / "docs" / "experiments") == "docs/experiments"


def test_outside_a_repository_below_the_current_directory_is_relative_else_absolute(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert repository_root(tmp_path) is None
    assert recorded_path(tmp_path / "runs" / "cartpole") == "runs/cartpole"
    outside = Path("/") / "nowhere-in-a-repo" / "runs"
    assert recorded_path(outside) == outside.as_posix()


def test_overrides_with_an_absolute_path_are_recorded_relative(tmp_path, monkeypatch):
    (tmp_path / ".git").mkdir()
    monkeypatch.chdir(tmp_path)
    assert recorded_override(f"sweep.root={tmp_path / 'docs' / 'experiments' / 'cartpole'}") == (
        "sweep.root=docs/experiments/cartpole")
    assert recorded_override("sweep.root=runs/x") == "sweep.root=runs/x"
    assert recorded_override("seed=3") == "seed=3"
    assert recorded_override("hydra.launcher.n_jobs=4") == "hydra.launcher.n_jobs=4"


def test_the_report_records_its_root_relative_to_the_repository(tmp_path, monkeypatch):
    (tmp_path / ".git").mkdir()
    root = make_experiment(tmp_path / "docs" / "experiments" / "cartpole", CARTPOLE)
    monkeypatch.chdir(tmp_path / "docs")  # wherever it is run from
    report = write_report(root, tmp_path / "out")
    assert "- Root: `docs/experiments/cartpole`" in report.read_text()
    assert '"root": "docs/experiments/cartpole"' in (report.parent / "tables.json").read_text()
    assert str(tmp_path) not in report.read_text() + (report.parent / "tables.json").read_text()
