"""Task: dimensions and start distribution from the env, success by the reward's own distance."""

from __future__ import annotations

import math

import numpy as np
import pytest

from qtl.errors import TaskError
from qtl.task import Task

CARTPOLE = {
    "name": "cartpole",
    "env": {"id": "qtl/CartPoleSwingUp-v0", "pole_length": 0.6},
    "horizon": 50,
    "angle_dims": [2],
    "success": {"threshold": 0.15, "last_steps": 20},
}


def test_cartpole_task_reads_the_env():
    task = Task.from_config(CARTPOLE)
    assert (task.state_dim, task.action_dim, task.feature_dim, task.gp_input_dim) == (4, 1, 5, 6)
    np.testing.assert_allclose(task.start_std, 0.1)
    assert task.reward.angle_dims == (2,)


def test_distance_is_the_pole_tip_distance_and_success_needs_the_whole_window():
    task = Task.from_config(CARTPOLE)
    upright = np.array([0.0, 0.0, math.pi, 0.0])
    down = np.array([0.0, 0.0, 0.0, 0.0])
    assert task.distance(upright[None])[0] == pytest.approx(0.0, abs=1e-12)
    assert task.distance(down[None])[0] == pytest.approx(1.2)  # 2 l below the target
    shifted = np.array([0.1, 0.0, math.pi, 0.0])
    assert task.distance(shifted[None])[0] == pytest.approx(0.1)
    states = np.stack([down] * 31 + [upright] * 20)
    assert task.succeeded(states)
    states[-5] = down
    assert not task.succeeded(states)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"env": {"id": "Pendulum-v1"}, "start": None}, "has no start_mean/start_std"),
        ({"env": {"id": "CartPole-v1"}}, "must have a 1-D Box action space"),
        ({"success": {"threshold": 0.1, "last_steps": 80}}, "last_steps <= horizon"),
        ({"env": {}}, "task.env.id is missing"),
    ],
)
def test_bad_tasks_are_named(change, message):
    with pytest.raises(TaskError, match=message):
        Task.from_config({**CARTPOLE, **change})


def test_any_box_env_with_start_and_reward_in_the_config():
    pendulum = {
        "name": "pendulum",
        "env": {"id": "Pendulum-v1"},
        "horizon": 30,
        "angle_dims": [],
        "start": {"mean": [1.0, 0.0, 0.0], "std": [0.05, 0.05, 0.1]},
        "reward": {"angle_dims": [], "target": [1.0, 0.0, 0.0], "weight": [[1, 0, 0], [0, 1, 0], [0, 0, 0]],
                   "width": 0.5},
        "success": {"threshold": 0.2, "last_steps": 10},
    }
    task = Task.from_config(pendulum)
    assert task.action_bound.tolist() == [2.0] and task.state_dim == 3
    assert task.reward(np.array([1.0, 0.0, 3.0])) == pytest.approx(1.0)
