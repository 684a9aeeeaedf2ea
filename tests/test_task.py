"""Task: dimensions and start distribution from the env, success by the reward's own distance."""

from __future__ import annotations

import math

import numpy as np
import pytest

from qtl.errors import TaskError
from qtl.task import Task, env_settings

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
        ({"success": {"threshold": 0.1, "last_steps": 80}}, "set task.success.last_steps to at most 50"),
        ({"success": {"threshold": 0.0, "last_steps": 8}}, "threshold > 0"),
        ({"env": {"id": "qtl/CartPoleSwingUp-v0", "horizon": 70}}, "task.env.horizon=70 disagrees with task.horizon"),
        ({"env": {"id": "qtl/CartPoleSwingUp-v0", "pole_mas": 2.0}}, "bad constructor kwargs"),
        ({"state_names": ["x", "v"]}, "names 2 dimensions, the state has 4"),
        ({"env": {}}, "task.env.id is missing"),
    ],
)
def test_bad_tasks_are_named(change, message):
    with pytest.raises(TaskError, match=message):
        Task.from_config({**CARTPOLE, **change})


PENDULUM = {
    "name": "pendulum",
    "env": {"id": "Pendulum-v1"},
    "horizon": 30,
    "angle_dims": [],
    "start": {"mean": [1.0, 0.0, 0.0], "std": [0.05, 0.05, 0.1]},
    "reward": {"angle_dims": [], "target": [1.0, 0.0, 0.0], "weight": [[1, 0, 0], [0, 1, 0], [0, 0, 0]], "width": 0.5},
    "success": {"threshold": 0.2, "last_steps": 10},
}


def test_any_box_env_with_start_and_reward_in_the_config():
    task = Task.from_config(PENDULUM)
    assert task.action_bound.tolist() == [2.0] and task.state_dim == 3
    assert task.reward(np.array([1.0, 0.0, 3.0])) == pytest.approx(1.0)


def test_the_one_horizon_reaches_the_env():
    task = Task.from_config({**CARTPOLE, "horizon": 30, "success": {"threshold": 0.15, "last_steps": 5}})
    with task.make_env() as env:
        assert env.unwrapped.horizon == 30
    # An old run's config names it twice, equal: still one horizon.
    old = Task.from_config({**CARTPOLE, "env": {**CARTPOLE["env"], "horizon": 50}})
    assert old.horizon == 50 and old.env_kwargs["horizon"] == 50


def test_an_env_without_a_horizon_kwarg_is_limited_by_gymnasium():
    task = Task.from_config({**PENDULUM, "horizon": 7, "success": {"threshold": 0.2, "last_steps": 2}})
    with task.make_env() as env:
        env.reset(seed=0)
        steps = 1
        while not env.step(env.action_space.sample())[3]:
            steps += 1
    assert steps == 7  # not Pendulum's own 200


def test_state_names_come_from_the_env_or_the_task():
    assert Task.from_config(CARTPOLE).state_names == ("x (m)", "ẋ (m/s)", "θ (rad)", "θ̇ (rad/s)")
    assert Task.from_config(PENDULUM).state_names == ("x[0]", "x[1]", "x[2]")
    named = Task.from_config({**PENDULUM, "state_names": ["cos", "sin", "rate"]})
    assert named.state_names == ("cos", "sin", "rate")


def test_env_settings_fill_in_the_defaults():
    full = {**CARTPOLE, "env": {**CARTPOLE["env"], "pole_mass": 0.5, "friction": 0.1, "horizon": 50}}
    assert env_settings(full) == env_settings(CARTPOLE)
    assert env_settings(CARTPOLE)["horizon"] == 50
    assert env_settings({**CARTPOLE, "env": {**CARTPOLE["env"], "pole_mass": 2.0}}) != env_settings(CARTPOLE)
