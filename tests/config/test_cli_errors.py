"""A user's own task YAML through ``qtl-train``: integers where floats are expected, and one-line composition errors."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import CLI_TINY, PENDULUM_TASK_TEMPLATE

pytestmark = pytest.mark.e2e

TASK = PENDULUM_TASK_TEMPLATE
FLOATS = "[[0.25, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]]"
INTEGERS = "[[0.25, 0, 0], [0, 1, 0], [0, 0, 0]]"
TINY = [a for a in CLI_TINY if not a.startswith("task.")]


def qtl_train(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    environ = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    return subprocess.run([sys.executable, "-m", "qtl", "hydra.searchpath=[file://my_configs]", *args], cwd=tmp_path,
                          capture_output=True, text=True, timeout=300, env=environ)


def write_task(tmp_path: Path, name: str, weight: str = FLOATS, target: str = "[1.0, 0.0, 0.0]") -> None:
    (tmp_path / "my_configs" / "task").mkdir(parents=True, exist_ok=True)
    (tmp_path / "my_configs" / "task" / f"{name}.yaml").write_text(TASK.format(weight=weight, target=target))


def test_integers_where_floats_are_expected_run_as_the_floats_do(tmp_path):
    write_task(tmp_path, "floats")
    write_task(tmp_path, "integers", weight=INTEGERS, target="[1, 0, 0]")
    runs = {}
    for name, threshold in (("floats", "1.0"), ("integers", "1")):
        done = qtl_train(tmp_path, f"task={name}", *TINY, f"task.success.threshold={threshold}",
                         f"hydra.run.dir={tmp_path / name}")
        assert done.returncode == 0, done.stderr
        runs[name] = (tmp_path / name / "metrics.csv").read_bytes()
    assert runs["integers"] == runs["floats"]  # 0 is 0.0: the same run, byte for byte


def test_an_integer_override_of_a_float_key_composes_as_its_float(tmp_path):
    write_task(tmp_path, "integers", weight=INTEGERS)
    done = qtl_train(tmp_path, "task=integers", "rule=forgetting", "rule.gamma=1", "--cfg", "job")
    assert done.returncode == 0, done.stderr
    assert "gamma: 1.0" in done.stdout and "- - 0.25" in done.stdout


@pytest.mark.parametrize(("weight", "target", "message"), [
    ('[["a", 0, 0], [0, 1, 0], [0, 0, 0]]', "[1, 0, 0]", "task.reward.weight must be a matrix of numbers"),
    ("[1, 0, 0]", "[1, 0, 0]", "task.reward.weight must be a matrix of numbers"),
    (INTEGERS, '["a", 0, 0]',
     "ValidationError raised while composing config: task.reward.target[0]: Value 'a' of type 'str' could not be "
     "converted to Float"),
])
def test_a_wrong_type_in_a_task_yaml_fails_in_one_line_that_says_where_and_why(tmp_path, weight, target, message):
    write_task(tmp_path, "bad", weight=weight, target=target)
    done = qtl_train(tmp_path, "task=bad", *TINY, f"hydra.run.dir={tmp_path / 'run'}")
    assert done.returncode == 1 and message in done.stderr, done.stderr
    assert done.stderr.strip().count("\n") == 0 and "Traceback" not in done.stderr
    assert not (tmp_path / "run" / "metrics.csv").exists() and not (tmp_path / "run" / "checkpoints").exists()


def test_a_gpu_that_is_not_there_is_one_line_before_any_work(tmp_path):
    """``device=cuda:99``: no machine of ours has it (none at all on a CPU machine); one line, no run directory."""
    environ = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    done = subprocess.run([sys.executable, "-m", "qtl", *TINY, "device=cuda:99", f"hydra.run.dir={tmp_path / 'run'}"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300, env=environ)
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("qtl-train: device='cuda:99', but "), done.stderr
    assert "use device=cpu" in lines[0] and not (tmp_path / "run" / "metrics.csv").exists()


def test_keys_for_a_node_that_is_null_in_its_yaml_are_one_line(tmp_path):
    """OmegaConf cannot merge keys into a null structured node (here task.search_reward); it raises its own
    AttributeError, not one of its errors: still one line that names the key, not a traceback."""
    environ = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    done = subprocess.run([sys.executable, "-m", "qtl", "task=mountaincar",
                           "task.search_reward={target:[0.5,null],widths:[0.3,null]}", *TINY,
                           f"hydra.run.dir={tmp_path / 'run'}"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300, env=environ)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and len(lines) == 1, done.stderr
    assert lines[0].startswith("qtl-train: cannot apply the override of task.search_reward: ") and "null" in lines[0]
    assert not (tmp_path / "run").exists()
