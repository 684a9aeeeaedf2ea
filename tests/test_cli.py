"""The installed ``qtl-train`` and ``python -m qtl``, end to end on a tiny budget, as a new user meets them."""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from qtl.checkpoint import run_lock
from tests.helpers import CLI_TINY as TINY
from tests.helpers import PENDULUM_TASK

pytestmark = pytest.mark.e2e


def run_cli(args: list[str], cwd: Path, **env: str) -> subprocess.CompletedProcess:
    environ = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"} | env
    return subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=300, env=environ)


def qtl(*args: str, cwd: Path, **env: str) -> subprocess.CompletedProcess:
    return run_cli([sys.executable, "-m", "qtl", *args], cwd, **env)


def read_rows(run_dir: Path) -> list[dict[str, str]]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def finished(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    """A tiny run of the installed ``qtl-train`` (output captured: stderr is no terminal)."""
    exe = shutil.which("qtl-train", path=str(Path(sys.executable).parent))
    assert exe is not None, "the console script qtl-train is not installed"
    cwd = tmp_path_factory.mktemp("cli")
    done = run_cli([exe, *TINY, f"hydra.run.dir={cwd / 'run'}"], cwd=cwd)
    assert done.returncode == 0, done.stderr
    return cwd / "run", done


def test_installed_cli_writes_everything_into_its_run_dir(finished):
    run_dir, done = finished
    assert "2 episodes, final return" in done.stdout
    assert (run_dir / ".hydra" / "config.yaml").is_file() and (run_dir / ".hydra" / "overrides.yaml").is_file()
    assert len(read_rows(run_dir)) == 2
    assert len(list((run_dir / "checkpoints").glob("episode_*.pt"))) == 2
    events = EventAccumulator(str(run_dir))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    assert {"eval/return", "policy/predicted_return", "model/smse", "time/model_fit_s",
            "time/policy_search_s", "theta/out0/noise_variance", "theta_p/out0/noise_variance",
            "transfer/fallback"} <= tags
    assert sorted(p.name for p in run_dir.parent.iterdir()) == ["run"]  # nothing in the cwd


def test_progress_bars_are_off_when_stderr_is_no_terminal(finished):
    _, done = finished
    assert "\r" not in done.stderr and "%|" not in done.stderr and "episode/s" not in done.stderr


def test_refused_run_leaves_the_run_there_untouched(finished, tmp_path):
    run_dir, _ = finished
    record = {p.name: p.read_text() for p in (run_dir / ".hydra").iterdir()}
    refused = qtl(*TINY, "seed=7", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert refused.returncode == 1
    assert "already holds a run's checkpoints" in refused.stderr and "nothing was overwritten" in refused.stderr
    assert {p.name: p.read_text() for p in (run_dir / ".hydra").iterdir()} == record
    assert len(read_rows(run_dir)) == 2


def test_resume_continues_in_the_run_and_leaves_nothing_in_the_cwd(finished, tmp_path):
    source, _ = finished
    run_dir = tmp_path / "run"
    shutil.copytree(source, run_dir)
    config = (run_dir / ".hydra" / "config.yaml").read_text()
    resumed = qtl(f"resume={run_dir}", "episodes=2", "threads=1", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    assert [r["episode"] for r in read_rows(run_dir)] == ["0", "1", "2"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # no stray outputs/<date>/<time>/
    assert "resuming" in (run_dir / "train.log").read_text()  # the run's own log continues
    assert (run_dir / ".hydra" / "config.yaml").read_text() == config


def test_resume_through_a_symlink_logs_each_line_once(finished, tmp_path):
    # E.g. a worktree whose docs/experiments links to another checkout's: Hydra's output directory is the
    # link, the resumed run the resolved path, and both are one train.log.
    source, _ = finished
    shutil.copytree(source, tmp_path / "run")
    (tmp_path / "link").symlink_to(tmp_path / "run", target_is_directory=True)
    before = (tmp_path / "run" / "train.log").read_text().count("\n")
    resumed = qtl("resume=link", "episodes=2", "threads=1", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    added = (tmp_path / "run" / "train.log").read_text().splitlines()[before:]
    assert any("episode 2" in line for line in added)
    assert len(added) == len(set(added)), "\n".join(added)


def test_a_run_in_use_by_another_process_is_refused_and_left_as_it_is(finished, tmp_path):
    # E.g. a sweep restarted while the old sweep's workers still run: the second process must not write there too.
    source, _ = finished
    run_dir = tmp_path / "run"
    shutil.copytree(source, run_dir)
    with run_lock(run_dir):  # this test process holds the run, as a live worker would
        refused = qtl(f"resume={run_dir}", "episodes=2", "threads=1", cwd=tmp_path)
        auto = qtl(*TINY, "resume=auto", f"hydra.run.dir={run_dir}", cwd=tmp_path)
    for done in (refused, auto):
        assert done.returncode == 1
        assert done.stderr.strip().count("\n") == 0 and "is in use by another qtl process (pid" in done.stderr
    assert [r["episode"] for r in read_rows(run_dir)] == ["0", "1"]
    assert len(list((run_dir / "checkpoints").glob("episode_*.pt"))) == 2
    resumed = qtl(f"resume={run_dir}", "episodes=2", "threads=1", cwd=tmp_path)  # released: it continues
    assert resumed.returncode == 0, resumed.stderr


def test_user_errors_are_one_line_on_stderr_and_in_the_log(finished, tmp_path):
    run_dir, _ = finished
    changed = qtl(f"resume={run_dir}", "seed=5", cwd=tmp_path)
    assert changed.returncode == 1
    assert changed.stderr.strip().count("\n") == 0 and "cannot change 'seed'" in changed.stderr
    assert "cannot change 'seed'" in (run_dir / "train.log").read_text()
    for args, message in [(["episdoes=1"], "episdoes"), (["episodes=abc"], "episodes=abc"),
                          (["task=nosuchtask"], "options: cartpole"), ([f"resume={tmp_path / 'nothing'}"],
                                                                       "does not exist")]:
        bad = qtl(*args, cwd=tmp_path)
        assert bad.returncode == 1 and message in bad.stderr
        assert bad.stderr.strip().count("\n") == 0, bad.stderr
    assert sorted(tmp_path.iterdir()) == []  # refused before Hydra made a run directory
    full = qtl("episdoes=1", cwd=tmp_path, HYDRA_FULL_ERROR="1")
    assert full.returncode == 1 and "Traceback" in full.stderr


@pytest.mark.parametrize(("args", "message"), [(["episodes=-1"], "episodes=-1"),
                                               (["random_episodes=0"], "random_episodes must be >= 1")])
def test_budgets_that_cannot_learn_fail_before_any_work(tmp_path, args, message):
    run_dir = tmp_path / "run"
    done = qtl(*TINY, *args, f"hydra.run.dir={run_dir}", cwd=tmp_path)
    assert done.returncode == 1 and message in done.stderr and "Traceback" not in done.stderr
    assert not (run_dir / ".hydra").exists() and not (run_dir / "metrics.csv").exists()
    assert message in (run_dir / "train.log").read_text()


def test_help_describes_the_keys(tmp_path):
    done = qtl("--help", cwd=tmp_path)
    assert done.returncode == 0
    assert "episodes [9]" in done.stdout and "learned episodes after them" in done.stdout
    assert "optimizer=lbfgs" in done.stdout and "task.horizon" in done.stdout


def test_byo_env_recipe_own_task_from_a_search_path(tmp_path):
    """docs/guide/byo-env.md's recipe: any Box env, its start and reward in the task file on a search path."""
    (tmp_path / "my_configs" / "task").mkdir(parents=True)
    (tmp_path / "my_configs" / "task" / "pendulum.yaml").write_text(PENDULUM_TASK)
    tiny = [a for a in TINY if not a.startswith("task.")]
    done = qtl("task=pendulum", "hydra.searchpath=[file://my_configs]", *tiny, f"hydra.run.dir={tmp_path / 'run'}",
               cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    returns = [float(r["return"]) for r in read_rows(tmp_path / "run")]
    # The task's saturating reward (in [0, 1] per step), not Pendulum's own negative cost.
    assert len(returns) == 2 and all(0.0 <= r <= 6.0 for r in returns)
