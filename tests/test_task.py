"""Task: dimensions and start distribution from the env, success by the reward's own distance."""

from __future__ import annotations

import math
import re
import sys

import gymnasium
import numpy as np
import pytest

from qtl.config.validate import checked_task
from qtl.episodes import random_actor, run_episode
from qtl.errors import TaskError
from qtl.task import DEFAULT_START_MIN_STD, Kinematics, Task, constructor_parameters, env_settings
from tests.toy_envs import spinner_task

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
        ({"env": {"id": "Pendulum-v1"}, "start": {"mean": [0.0, 0.0, 0.0]}}, "start_std: set task.start.std too"),
        ({"env": {"id": "CartPole-v1"}}, "qtl needs continuous actions"),
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
        checked_task({**CARTPOLE, **change})


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


# -- any gymnasium env: action bounds, refused spaces, "module:EnvId" ids, action repeat ---------------------------


class PointEnv(gymnasium.Env):
    """A point x' = x + u (clipped to its bounds) with any action and observation space; records the actions it got."""

    def __init__(self, low=(-1.0,), high=(1.0,), dtype=np.float32, action_space=None, observation_space=None):
        self.action_space = action_space or gymnasium.spaces.Box(np.asarray(low, dtype), np.asarray(high, dtype))
        self.observation_space = observation_space or gymnasium.spaces.Box(-np.inf, np.inf, (1,), dtype)
        self.received: list[np.ndarray] = []

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.steps, self.x = 0, np.zeros(1, np.float32)
        return self.x.copy(), {}

    def step(self, action):
        self.received.append(np.array(action, copy=True))
        self.steps += 1
        self.x = self.x + np.float32(np.sum(action))
        return self.x.copy(), -1.0, False, False, {}


@pytest.fixture(scope="module", autouse=True)
def point_env():
    """``test/Point-v0`` registered for this module's tests."""
    gymnasium.register("test/Point-v0", entry_point=PointEnv)
    yield
    gymnasium.registry.pop("test/Point-v0")


def point(**env) -> dict:
    """A task config of ``test/Point-v0`` (1-D state) with ``env`` as constructor kwargs."""
    return {
        "name": "point",
        "env": {"id": "test/Point-v0", **env},
        "horizon": 6,
        "start": {"mean": [0.0], "std": [0.1]},
        "reward": {"angle_dims": [], "target": [0.0], "weight": [[1.0]], "width": 1.0},
        "success": {"threshold": 0.5, "last_steps": 2},
    }


def wrappers(env: gymnasium.Env) -> list[str]:
    """The class names of ``env``'s wrapper chain, outermost first, down to the raw env."""
    names = [type(env).__name__]
    while hasattr(env, "env"):
        env = env.env
        names.append(type(env).__name__)
    return names


def test_asymmetric_action_bounds_are_centred_onto_the_symmetric_range():
    task = Task.from_config(point(low=(-1.0, 0.0), high=(3.0, 0.5)))
    np.testing.assert_array_equal(task.action_bound, [2.0, 0.25])
    np.testing.assert_array_equal(task.action_center, [1.0, 0.25])
    with task.make_env() as env:
        assert wrappers(env)[0] == "CenteredAction"
        np.testing.assert_array_equal(env.action_space.high, [2.0, 0.25])
        np.testing.assert_array_equal(env.action_space.low, [-2.0, -0.25])
        env.reset(seed=0)
        env.step(np.float32([0.5, -0.25]))
        np.testing.assert_array_equal(env.unwrapped.received[-1], np.float32([1.5, 0.0]))


def test_symmetric_bounds_give_todays_env():
    task = Task.from_config(point(low=(-2.0,), high=(2.0,)))
    assert task.action_center is None and task.action_repeat == 1
    plain = gymnasium.make("test/Point-v0", low=(-2.0,), high=(2.0,), max_episode_steps=6)
    with task.make_env() as env, plain:
        assert wrappers(env) == wrappers(plain)
        assert env.action_space == plain.action_space
    assert task.env_kwargs == {"low": (-2.0,), "high": (2.0,), "max_episode_steps": 6}
    np.testing.assert_array_equal(task.action_bound, [2.0])
    pendulum = Task.from_config(PENDULUM)
    assert pendulum.action_center is None and "CenteredAction" not in wrappers(pendulum.make_env())


def test_a_float32_env_with_asymmetric_bounds_runs_an_episode_end_to_end():
    task = Task.from_config(point(low=(-0.3,), high=(0.7,)))
    with task.make_env() as env:
        episode = run_episode(env, task, random_actor(task, np.random.default_rng(0)), seed=0)
        received = np.concatenate(env.unwrapped.received)
    assert episode.states.shape == (7, 1) and episode.actions.shape == (6, 1) and episode.states.dtype == np.float64
    assert received.dtype == np.float32 and ((received >= np.float32(-0.3)) & (received <= np.float32(0.7))).all()
    np.testing.assert_allclose(received, episode.actions[:, 0] + 0.2, atol=1e-6)  # the centre, 0.2, plus the action
    np.testing.assert_allclose(np.diff(episode.states[:, 0]), received, atol=1e-6)
    np.testing.assert_allclose(episode.rewards, np.exp(-0.5 * episode.states[1:, 0] ** 2), rtol=1e-6)


@pytest.mark.parametrize(
    ("low", "high"), [((-np.inf,), (1.0,)), ((-1.0,), (np.inf,)), ((0.5,), (0.5,)), ((-1.0, 0.0), (1.0, 0.0))]
)
def test_infinite_or_zero_width_action_bounds_are_refused(low, high):
    with pytest.raises(TaskError, match="must have finite action bounds low < high"):
        checked_task(point(low=low, high=high))


BOX = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)


@pytest.mark.parametrize(
    ("spaces", "message"),
    [
        ({"action_space": gymnasium.spaces.Discrete(3)}, "qtl needs continuous actions .a 1-D Box.: PILCO's policy"),
        ({"action_space": gymnasium.spaces.MultiDiscrete([3, 2])}, "qtl needs continuous actions"),
        ({"action_space": gymnasium.spaces.MultiBinary(2)}, "qtl needs continuous actions"),
        ({"action_space": gymnasium.spaces.Box(-1, 1, (1,), np.int64)}, "qtl needs continuous actions"),
        ({"observation_space": gymnasium.spaces.Dict({"x": BOX})}, "Dict observation space .*FlattenObservation"),
        ({"observation_space": gymnasium.spaces.Tuple((BOX, BOX))}, "Tuple observation space .*FlattenObservation"),
        ({"action_space": gymnasium.spaces.Tuple((BOX, BOX))}, "Tuple action space .*or give a 1-D Box"),
        ({"observation_space": gymnasium.spaces.Box(0, 255, (8, 8, 3), np.uint8)}, "pixels are not states"),
        ({"observation_space": gymnasium.spaces.Box(0, 255, (16,), np.uint8)}, "pixels are not states"),
        ({"observation_space": gymnasium.spaces.Box(-1.0, 1.0, (2, 2), np.float32)}, "qtl models states with a GP"),
        ({"observation_space": gymnasium.spaces.Discrete(4)}, "must have a 1-D Box observation space"),
        ({"action_space": gymnasium.spaces.Box(-1.0, 1.0, (2, 2), np.float32)}, "must have a 1-D Box action space"),
    ],
)
def test_spaces_qtl_cannot_learn_with_are_refused_saying_why(spaces, message):
    with pytest.raises(TaskError, match=message):
        checked_task(point(**spaces))


ENV_MODULE = '''
import gymnasium
import numpy as np


class TinyEnv(gymnasium.Env):
    def __init__(self, gain=1.0):
        self.gain = gain
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(1, np.float32), {}

    def step(self, action):
        return np.float32(self.gain) * np.asarray(action, np.float32), 0.0, False, False, {}


gymnasium.register("TinyEnv-v0", entry_point=TinyEnv)
'''


@pytest.fixture
def env_package(tmp_path, monkeypatch):
    """A package ``tiny_envs`` on sys.path: ``tiny_envs.reg`` registers ``TinyEnv-v0``, ``tiny_envs.none`` nothing."""
    package = tmp_path / "tiny_envs"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "reg.py").write_text(ENV_MODULE)
    (package / "none.py").write_text("X = 1\n")
    (package / "needs.py").write_text("import not_installed_physics_xyz\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "tiny_envs"
    for name in [m for m in sys.modules if m.split(".")[0] == "tiny_envs"]:
        del sys.modules[name]
    gymnasium.registry.pop("TinyEnv-v0", None)


def test_a_module_env_id_works_everywhere_the_id_is_used(env_package):
    cfg = {**point(), "env": {"id": "tiny_envs.reg:TinyEnv-v0", "gain": 2.0}}
    assert "tiny_envs.reg" not in sys.modules
    assert set(constructor_parameters(cfg["env"]["id"])) == {"gain"}  # imports the module itself
    assert env_settings(cfg) == {"id": "tiny_envs.reg:TinyEnv-v0", "gain": 2.0, "max_episode_steps": 6}
    task = Task.from_config(cfg)
    with task.make_env() as env:
        env.reset(seed=0)
        assert env.step(np.float32([0.5]))[0][0] == 1.0 and env.unwrapped.gain == 2.0


@pytest.mark.parametrize("call", [Task.from_config, env_settings])
def test_a_missing_module_says_what_to_install(call, env_package):
    cfg = {**point(), "env": {"id": "foo_envs_nowhere.bar:Baz-v0"}}
    message = (
        "cannot import module 'foo_envs_nowhere' for task.env.id='foo_envs_nowhere.bar:Baz-v0': "
        "pip install foo_envs_nowhere (or the package that provides it)"
    )
    with pytest.raises(TaskError, match=re.escape(message)):
        call(cfg)
    missing_dependency = r"cannot import module 'not_installed_physics_xyz' .*: pip install not_installed_physics_xyz "
    with pytest.raises(TaskError, match=missing_dependency):
        call({**cfg, "env": {"id": "tiny_envs.needs:Baz-v0"}})


def test_a_module_that_does_not_register_the_id_is_named(env_package):
    cfg = {**point(), "env": {"id": "tiny_envs.none:TinyEnv-v0"}}
    with pytest.raises(TaskError, match=r"task.env.id='tiny_envs.none:TinyEnv-v0': .*does not register 'TinyEnv-v0'"):
        checked_task(cfg)


def test_action_repeat_holds_each_action_and_the_horizon_counts_held_steps():
    task = Task.from_config({**point(), "action_repeat": 3})
    assert task.env_kwargs["max_episode_steps"] == 18 and not task.reward_from_env
    with task.make_env() as env:
        assert "ActionRepeat" in wrappers(env)
        env.reset(seed=0)
        steps, truncated = 0, False
        while not truncated:
            _, reward, _, truncated, _ = env.step(np.float32([0.25]))
            steps += 1
            assert reward == -3.0  # the env's rewards summed over the held step
        assert steps == 6 and env.unwrapped.steps == 18


def test_action_repeat_multiplies_an_env_horizon_kwarg_and_one_gives_todays_env():
    held = Task.from_config({**CARTPOLE, "action_repeat": 2})
    assert held.horizon == 50 and held.env_kwargs["horizon"] == 100 and not held.reward_from_env
    with held.make_env() as env:
        assert env.unwrapped.horizon == 100
    today, one = Task.from_config(CARTPOLE), Task.from_config({**CARTPOLE, "action_repeat": 1})
    assert one.env_kwargs == today.env_kwargs == {"pole_length": 0.6, "horizon": 50} and one.reward_from_env
    assert wrappers(one.make_env()) == wrappers(today.make_env()) and "ActionRepeat" not in wrappers(one.make_env())


@pytest.mark.parametrize("repeat", [0, -1, 1.5, "2"])
def test_action_repeat_below_one_step_is_refused(repeat):
    with pytest.raises(TaskError, match=r"task\.action_repeat must be a whole number of env steps >= 1"):
        checked_task({**point(), "action_repeat": repeat})
    with pytest.raises(TaskError, match=r"task\.action_repeat must"):
        env_settings({**point(), "action_repeat": repeat})


def test_env_settings_tell_tasks_apart_by_their_action_repeat():
    today = env_settings(CARTPOLE)
    assert env_settings({**CARTPOLE, "action_repeat": 1}) == today and "task.action_repeat" not in today
    held = env_settings({**CARTPOLE, "action_repeat": 2})
    assert held != today and held["task.action_repeat"] == 2 and held["horizon"] == 100
    # An env with an action_repeat kwarg of its own keeps it apart from the task's.
    car = {"name": "car", "env": {"id": "qtl/MountainCar-v0"}, "horizon": 80, "action_repeat": 2,
           "success": {"threshold": 0.1, "last_steps": 10}}
    assert env_settings(car)["action_repeat"] == 5 and env_settings(car)["task.action_repeat"] == 2
    assert Task.from_config(car).env_kwargs != Task.from_config({**car, "action_repeat": 1}).env_kwargs


def test_a_task_with_no_start_distribution_anywhere_estimates_it():
    task = Task.from_config(spinner_task())
    assert task.start_estimated and task.start_mean is None and task.start_std is None
    assert task.start_min_std == DEFAULT_START_MIN_STD and task.reset_options is None
    with pytest.raises(TaskError, match="estimated from data"):
        task.start_distribution()
    given = Task.from_config(spinner_task(start={"mean": [math.pi, 0.0, 0.0], "std": [0.1, 0.1, 0.0]}))
    assert not given.start_estimated and given.start_std.tolist() == [0.1, 0.1, 0.0]
    assert not Task.from_config(CARTPOLE).start_estimated  # the env's start_mean/start_std, as before
    floored = Task.from_config(spinner_task(start={"min_std": 0.2}, reset_options={"angle": 0.5}))
    assert floored.start_estimated and floored.start_min_std == 0.2 and floored.reset_options == {"angle": 0.5}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"start": {"min_std": 0.0}}, "task.start.min_std must be a positive std"),
        ({"start": {"std": [0.1, 0.1, 0.1]}}, "start_mean: set task.start.mean too"),
        ({"reset_options": [1, 2]}, "task.reset_options must be a mapping"),
    ],
)
def test_bad_start_settings_are_named(change, message):
    with pytest.raises(TaskError, match=message):
        checked_task(spinner_task(**change))


def test_estimated_start_takes_the_circular_mean_of_angles_and_floors_the_std():
    task = Task.from_config(spinner_task(start={"min_std": 0.01}))
    # θ straddles ±π (an env wrapping into [−π, π)); ω spread; p constant (floored).
    x0 = np.array([[math.pi - 0.1, 0.2, 0.5], [-math.pi + 0.1, -0.2, 0.5],
                   [math.pi - 0.05, 0.1, 0.5], [-math.pi + 0.05, -0.1, 0.5]], dtype=np.float64)
    mean, std = task.estimate_start(x0)
    assert abs(mean[0]) == pytest.approx(math.pi, abs=1e-12)  # not 0, the plain mean
    assert std[0] == pytest.approx(math.sqrt((0.1**2 + 0.1**2 + 0.05**2 + 0.05**2) / 4), rel=1e-12)
    assert mean[1] == pytest.approx(0.0, abs=1e-15) and std[1] == pytest.approx(np.std([0.2, -0.2, 0.1, -0.1]))
    assert mean[2] == 0.5 and std[2] == 0.01
    # The same start seen on [0, 2π) gives the same distribution on the circle.
    shifted = x0.copy()
    shifted[:, 0] = np.mod(shifted[:, 0], 2 * math.pi)
    mean2, std2 = task.estimate_start(shifted)
    assert math.cos(mean2[0] - mean[0]) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(std2, std, rtol=1e-12)
    one_mean, one_std = task.estimate_start(x0[:1])
    assert one_mean[0] == pytest.approx(math.pi - 0.1, abs=1e-12) and one_std.tolist() == [0.01] * 3
    with pytest.raises(ValueError, match="initial states must be `N x 3`"):
        task.estimate_start(np.zeros((0, 3)))


def test_the_first_observation_is_the_first_episodes_reset_with_the_reset_options():
    task = Task.from_config(spinner_task())
    with task.make_env() as env:
        expected, _ = env.reset(seed=11)
    np.testing.assert_array_equal(task.first_observation(11), expected)
    assert abs(task.first_observation(11)[0]) > 3.0  # θ ≈ ±π
    optioned = Task.from_config(spinner_task(reset_options={"angle": 0.5}))
    assert abs(optioned.first_observation(11)[0] - 0.5) <= 0.05


def test_an_early_ended_episode_is_judged_on_the_states_it_has():
    task = Task.from_config(spinner_task(success={"threshold": 0.3, "last_steps": 5}))
    at_goal, away = np.array([0.05, 0.0, 0.0]), np.array([math.pi, 0.0, 0.9])
    assert task.succeeded(np.stack([at_goal, at_goal, at_goal]))  # 2 steps, ended at the goal: fewer than 5 states
    assert not task.succeeded(np.stack([at_goal, at_goal, away]))  # ended away from it (off the track)
    assert not task.succeeded(np.stack([away, at_goal, at_goal]))  # the whole (short) window counts
    assert task.succeeded(np.stack([away] * 4 + [at_goal] * 5))  # a full window: only its last 5 states


def test_search_reward_is_parsed_with_null_entries_left_out():
    task = Task.from_config({**CARTPOLE, "search_reward": {"target": [0.0, None, math.pi, None],
                                                           "widths": [0.7, None, 2.1, None]}})
    target, widths = task.search_cost
    np.testing.assert_array_equal(target, [0.0, 0.0, math.pi, 0.0])
    np.testing.assert_array_equal(widths, [0.7, math.inf, 2.1, math.inf])
    assert Task.from_config(CARTPOLE).search_cost is None
    assert task.search_cost_angles == "wrapped"


def test_search_reward_angles_are_checked():
    search = {"target": [0.0, None, math.pi, None], "widths": [0.7, None, 2.1, None]}
    task = Task.from_config({**CARTPOLE, "search_reward": {**search, "angles": "absolute"}})
    assert task.search_cost_angles == "absolute"
    with pytest.raises(TaskError, match=r"task\.search_reward\.angles must be one of wrapped, absolute, got 'raw'"):
        checked_task({**CARTPOLE, "search_reward": {**search, "angles": "raw"}})


@pytest.mark.parametrize("search", [
    {"target": [0.0, None, 3.0], "widths": [0.7, None, 2.1]},
    {"target": [0.0, None, 3.0, None], "widths": [None, None, None, None]},
    {"target": [None, None, 3.0, None], "widths": [0.7, None, 2.1, None]},
    {"target": [0.0, None, 3.0, None], "widths": [-0.7, None, 2.1, None]},
])
def test_bad_search_rewards_are_refused(search):
    with pytest.raises(TaskError, match=r"task\.search_reward needs"):
        checked_task({**CARTPOLE, "search_reward": search})


def test_kinematics_take_the_envs_control_period_times_the_action_repeat():
    kinematics = {"positions": [0, 2], "velocities": [1, 3]}
    task = Task.from_config({**CARTPOLE, "env": {**CARTPOLE["env"], "dt": 0.05}, "kinematics": kinematics})
    assert task.kinematics == Kinematics((0, 2), (1, 3), 0.05)
    held = Task.from_config({**CARTPOLE, "horizon": 20, "action_repeat": 3, "kinematics": kinematics})
    assert held.kinematics.period == pytest.approx(0.3)
    given = Task.from_config({**CARTPOLE, "kinematics": {**kinematics, "period": 0.2}})
    assert given.kinematics.period == 0.2
    assert Task.from_config(CARTPOLE).kinematics is None
    empty = {"positions": [], "velocities": [], "period": None, "weight": 0.5}  # the schema's default node
    assert Task.from_config({**CARTPOLE, "kinematics": empty}).kinematics is None
    checked_task({**CARTPOLE, "kinematics": empty})  # declares none: nothing to check


@pytest.mark.parametrize(("kinematics", "message"), [
    ({"positions": [0], "velocities": []}, "as many velocities as positions"),
    ({"positions": [0, 2], "velocities": [1, 2]}, "distinct state indices below 4"),
    ({"positions": [0], "velocities": [1], "period": -0.1}, "period must be a control period > 0"),
    ({"positions": [0], "velocities": [1], "weight": -0.5}, r"weight must be in \[0, 1\]"),
])
def test_bad_kinematics_are_refused(kinematics, message):
    with pytest.raises(TaskError, match=message):
        checked_task({**CARTPOLE, "kinematics": kinematics})


def test_kinematics_without_a_period_need_an_env_with_dt(point_env):
    with pytest.raises(TaskError, match=r"task\.kinematics\.period is not set and the env has no dt"):
        checked_task({**point(), "kinematics": {"positions": [0], "velocities": [0]}})
