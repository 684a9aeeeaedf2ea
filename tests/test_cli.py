"""The installed ``qtl-train`` and ``python -m qtl``, end to end on a tiny budget."""

from __future__ import annotations

import csv
import shutil
import subprocess
import sys
from pathlib import Path

from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from tests.helpers import CLI_TINY as TINY


def run_cli(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=300)


def test_installed_cli_writes_everything_into_its_run_dir(tmp_path):
    exe = shutil.which("qtl-train", path=str(Path(sys.executable).parent))
    assert exe is not None, "the console script qtl-train is not installed"
    run_dir = tmp_path / "run"
    done = run_cli([exe, *TINY, f"hydra.run.dir={run_dir}"], cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "2 episodes, final return" in done.stdout
    assert (run_dir / ".hydra" / "config.yaml").is_file()
    with open(run_dir / "metrics.csv", newline="") as f:
        assert len(list(csv.DictReader(f))) == 2
    assert len(list((run_dir / "checkpoints").glob("episode_*.pt"))) == 2
    events = EventAccumulator(str(run_dir))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    assert {"eval/return", "policy/predicted_return", "model/smse", "time/model_fit_s",
            "time/policy_search_s", "theta/out0/noise_variance", "theta_p/out0/noise_variance",
            "transfer/fallback"} <= tags
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # nothing in the cwd

    resumed = run_cli([exe, f"resume={run_dir}", "episodes=2", "threads=1"], cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr
    with open(run_dir / "metrics.csv", newline="") as f:
        assert [r["episode"] for r in csv.DictReader(f)] == ["0", "1", "2"]


def test_python_dash_m_qtl_reports_bad_input(tmp_path):
    bad = run_cli([sys.executable, "-m", "qtl", "episdoes=1"], cwd=tmp_path)
    assert bad.returncode != 0 and "episdoes" in bad.stderr
    missing = run_cli([sys.executable, "-m", "qtl", f"resume={tmp_path / 'nothing'}"], cwd=tmp_path)
    assert missing.returncode != 0 and "does not exist" in missing.stderr
    changed = run_cli([sys.executable, "-m", "qtl", f"resume={tmp_path}", "seed=5"], cwd=tmp_path)
    assert changed.returncode != 0


PENDULUM_TASK = """\
name: pendulum
env:
  id: Pendulum-v1
horizon: 6
angle_dims: []
policy_size: 4
start:
  mean: [1.0, 0.0, 0.0]
  std: [0.05, 0.05, 0.1]
reward:
  angle_dims: []
  target: [1.0, 0.0, 0.0]
  weight: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]]
  width: 0.5
success:
  threshold: 0.2
  last_steps: 2
"""


def test_readme_recipe_own_task_from_a_search_path(tmp_path):
    """The README's "add your own task": any Box env, start and reward in the task file."""
    (tmp_path / "my_configs" / "task").mkdir(parents=True)
    (tmp_path / "my_configs" / "task" / "pendulum.yaml").write_text(PENDULUM_TASK)
    tiny = [a for a in TINY if not a.startswith("task.")]
    done = run_cli([sys.executable, "-m", "qtl", "task=pendulum", "hydra.searchpath=[file://my_configs]", *tiny,
                    f"hydra.run.dir={tmp_path / 'run'}"], cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    with open(tmp_path / "run" / "metrics.csv", newline="") as f:
        returns = [float(r["return"]) for r in csv.DictReader(f)]
    # The task's saturating reward (in [0, 1] per step), not Pendulum's own negative cost.
    assert len(returns) == 2 and all(0.0 <= r <= 6.0 for r in returns)
