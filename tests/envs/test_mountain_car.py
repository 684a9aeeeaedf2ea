"""Tests of the continuous mountain car: gymnasium API, the map, power factors, reward, kwargs."""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import qtl.envs  # noqa: F401  (registers the ids)
from qtl.envs.mountain_car import (
    GOAL_POSITION,
    MAX_POSITION,
    MAX_SPEED,
    MIN_POSITION,
    MountainCarEnv,
    map_step,
)
from qtl.envs.rewards import SaturatingReward

ENV_ID = "qtl/MountainCar-v0"
START = np.array([-0.5, 0.0])


def reaches_goal(env: MountainCarEnv, policy: Callable[[np.ndarray], float]) -> bool:
    """Whether `policy(state) -> throttle` reaches x >= 0.5 within the horizon from START."""
    _, info = env.reset(seed=0, options={"state": START})
    for _ in range(env.horizon):
        _, _, _, truncated, info = env.step(np.array([policy(info["state"])]))
        if info["state"][0] >= GOAL_POSITION:
            return True
        if truncated:
            break
    return False


def full_throttle(_: np.ndarray) -> float:
    return 1.0


def bang_bang(state: np.ndarray) -> float:
    """Push along the velocity: pumps energy into the swing."""
    return 1.0 if state[1] > 0 else -1.0


# ---- gymnasium API ----------------------------------------------------------------------------
@pytest.mark.parametrize(("render_mode", "obs_noise_std"), [(None, 0.0), ("rgb_array", 0.0), (None, 0.01)])
def test_check_env(render_mode: str | None, obs_noise_std: float) -> None:
    env = gymnasium.make(ENV_ID, render_mode=render_mode, obs_noise_std=obs_noise_std)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
    messages = [str(w.message) for w in caught]
    if obs_noise_std == 0:
        assert not messages  # finite bounds: a fully clean check
    else:
        assert all("infinity" in m for m in messages)  # noise is unbounded


def test_spaces_and_no_time_limit_wrapper() -> None:
    env = gymnasium.make(ENV_ID)
    assert env.spec is not None and env.spec.max_episode_steps is None
    assert env.observation_space.dtype == np.float64
    np.testing.assert_array_equal(env.observation_space.low, [MIN_POSITION, -MAX_SPEED])
    np.testing.assert_array_equal(env.observation_space.high, [MAX_POSITION, MAX_SPEED])
    np.testing.assert_array_equal(env.action_space.low, [-1.0])
    np.testing.assert_array_equal(env.action_space.high, [1.0])


def test_reset_determinism() -> None:
    env = MountainCarEnv(obs_noise_std=0.001)
    actions = np.random.default_rng(0).uniform(-1, 1, size=20)

    def rollout(seed: int) -> np.ndarray:
        obs, _ = env.reset(seed=seed)
        return np.array([obs] + [env.step(np.array([a]))[0] for a in actions])

    np.testing.assert_array_equal(rollout(5), rollout(5))
    assert not np.allclose(rollout(5), rollout(6))


def test_start_distribution_attributes() -> None:
    env = MountainCarEnv()
    np.testing.assert_array_equal(env.start_mean, [-0.5, 0.0])
    np.testing.assert_array_equal(env.start_std, [0.05, 1e-4])
    env.reset(seed=0)
    starts = np.array([env.reset()[1]["state"] for _ in range(4000)])
    np.testing.assert_allclose(starts.mean(0), env.start_mean, atol=3e-3)
    np.testing.assert_allclose(starts.std(0), env.start_std, rtol=0.05)
    custom = MountainCarEnv(start_mean=(-0.3, 0.01), start_std=(0.0, 0.0))
    np.testing.assert_array_equal(custom.reset(seed=0)[0], [-0.3, 0.01])


def test_truncation_termination_and_info_state() -> None:
    env = MountainCarEnv(horizon=6, obs_noise_std=0.01)
    obs, info = env.reset(seed=1)
    assert not np.array_equal(obs, info["state"])
    for t in range(1, 7):
        obs, reward, terminated, truncated, info = env.step(np.array([1.0]))
        assert terminated is False
        assert truncated is (t == 6)
        np.testing.assert_array_equal(info["state"], env.state)
        assert info["state"] is not env.state
        assert reward == env.reward_spec(info["state"])


def test_goal_is_not_terminal() -> None:
    env = MountainCarEnv(power=3.0)
    env.reset(seed=0, options={"state": START})
    for _ in range(env.horizon - 1):
        _, _, terminated, truncated, _ = env.step(np.ones(1))
        assert not terminated and not truncated
    assert env.state[0] >= GOAL_POSITION


def test_step_before_reset_raises() -> None:
    with pytest.raises(gymnasium.error.ResetNeeded):
        MountainCarEnv().step(np.zeros(1))


# ---- the map ----------------------------------------------------------------------------------
def test_map_step_formula() -> None:
    x, v, a, power = -0.3, 0.01, 0.7, 1.5
    v_new = v + 0.001 * power * a - 0.0025 * math.cos(3 * x)
    assert map_step(x, v, a, power) == pytest.approx((x + v_new, v_new), rel=1e-15)
    assert map_step(0.3, 0.069, 1.0, 3.0)[1] == MAX_SPEED  # speed clip
    assert map_step(0.59, 0.05, 1.0, 1.0)[0] == MAX_POSITION  # right end clips the position


def test_a_negative_power_reverses_the_engine() -> None:
    """power = −1 mirrors the actuator: throttle a there moves the car as throttle −a does at power 1."""
    env, mirror = MountainCarEnv(power=-1.0), MountainCarEnv(power=1.0)
    for e in (env, mirror):
        e.reset(seed=3)
    for a in (0.8, -0.4, 1.0):
        assert np.array_equal(env.step(np.array([a]))[0], mirror.step(np.array([-a]))[0])
    assert map_step(-0.3, 0.01, 0.7, -1.0) == map_step(-0.3, 0.01, -0.7, 1.0)


def test_one_decision_is_action_repeat_map_steps() -> None:
    env = MountainCarEnv(action_repeat=5)
    env.reset(options={"state": START})
    x, v = START
    for _ in range(5):
        x, v = map_step(x, v, 0.4, 1.0)
    np.testing.assert_array_equal(env.step(np.array([0.4]))[4]["state"], [x, v])


def test_left_wall_zeroes_velocity() -> None:
    assert map_step(-1.19, -0.05, -1.0, 1.0) == (MIN_POSITION, 0.0)
    env = MountainCarEnv(action_repeat=1)
    env.reset(options={"state": [-1.19, -0.05]})
    np.testing.assert_array_equal(env.step(np.array([-1.0]))[4]["state"], [MIN_POSITION, 0.0])


def test_actions_are_clipped() -> None:
    env = MountainCarEnv()

    def after(a: float) -> np.ndarray:
        env.reset(options={"state": START})
        return env.step(np.array([a]))[4]["state"]

    np.testing.assert_array_equal(after(7.0), after(1.0))
    np.testing.assert_array_equal(after(-7.0), after(-1.0))


@pytest.mark.parametrize(("power", "climbs"), [(0.5, False), (1.0, False), (1.5, False), (3.0, True)])
def test_full_throttle_climbs_only_at_300_percent(power: float, climbs: bool) -> None:
    assert reaches_goal(MountainCarEnv(power=power), full_throttle) is climbs


@pytest.mark.parametrize("power", [0.5, 1.0, 1.5])
def test_swinging_reaches_the_goal(power: float) -> None:
    assert reaches_goal(MountainCarEnv(power=power), bang_bang)


def test_power_kwarg_through_make_changes_dynamics() -> None:
    strong = gymnasium.make(ENV_ID, power=3.0)
    base = gymnasium.make(ENV_ID)
    assert strong.unwrapped.power == 3.0
    s0 = strong.reset(seed=0)[0]
    b0 = base.reset(seed=0)[0]
    np.testing.assert_array_equal(s0, b0)
    assert strong.step(np.ones(1))[0][1] > base.step(np.ones(1))[0][1]


# ---- reward -----------------------------------------------------------------------------------
@pytest.mark.parametrize("velocity_weight", [0.0, 100.0])
def test_reward_equals_closed_form(velocity_weight: float) -> None:
    width = 0.25
    env = MountainCarEnv(velocity_weight=velocity_weight)
    spec = env.reward_spec
    assert isinstance(spec, SaturatingReward) and spec.angle_dims == () and spec.width == width
    rng = np.random.default_rng(0)
    states = np.stack([rng.uniform(-1.2, 0.6, 300), rng.uniform(-0.07, 0.07, 300)], axis=-1)
    d2 = (states[:, 0] - GOAL_POSITION) ** 2 + velocity_weight * states[:, 1] ** 2
    np.testing.assert_allclose(spec(states), np.exp(-d2 / (2 * width**2)), rtol=1e-12)
    env.reset(seed=0)
    for a in rng.uniform(-1, 1, 10):
        _, reward, _, _, info = env.step(np.array([a]))
        x, v = info["state"]
        d2 = (x - GOAL_POSITION) ** 2 + velocity_weight * v**2
        assert reward == pytest.approx(math.exp(-d2 / (2 * width**2)), rel=1e-12)


def test_reward_is_one_at_the_goal_and_near_zero_in_the_valley() -> None:
    spec = MountainCarEnv().reward_spec
    assert spec(np.array([GOAL_POSITION, 0.0])) == 1.0
    assert spec(START) < 1e-3
    assert spec(np.array([-math.pi / 6, 0.0])) < 1e-3  # the valley floor
    assert spec(np.array([MIN_POSITION, 0.0])) < 1e-9


# ---- kwargs -----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("power", 0.0),
        ("power", float("inf")),
        ("action_repeat", 0),
        ("action_repeat", 2.0),
        ("horizon", 0),
        ("horizon", -80),
        ("start_mean", (-0.5,)),
        ("start_mean", (-2.0, 0.0)),
        ("start_std", (-0.05, 0.0)),
        ("start_std", 0.05),
        ("velocity_weight", -1.0),
        ("reward_width", 0.0),
        ("obs_noise_std", -0.01),
        ("render_mode", "human"),
    ],
)
def test_bad_kwargs_raise(name: str, value: object) -> None:
    with pytest.raises(ValueError, match=name):
        MountainCarEnv(**{name: value})


# ---- rendering --------------------------------------------------------------------------------
def test_render_rgb_array() -> None:
    env = MountainCarEnv(render_mode="rgb_array")
    env.reset(options={"state": START})
    valley = env.render()
    assert valley is not None and valley.dtype == np.uint8 and valley.ndim == 3
    assert valley.shape[2] == 3
    env.reset(options={"state": [GOAL_POSITION, 0.0]})
    goal = env.render()
    assert goal is not None and goal.shape == valley.shape and np.any(goal != valley)


def test_render_without_mode_warns() -> None:
    env = MountainCarEnv()
    env.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert env.render() is None
