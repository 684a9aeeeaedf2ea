"""Tests of the quadcopter and helicopter environments (`envs/aircraft.py`)."""

from __future__ import annotations

import itertools
import math
import re

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import qtl.envs  # noqa: F401  (registers the ids)
from qtl.envs.aircraft import (
    GRAVITY,
    AircraftEnv,
    Autopilot,
    HelicopterEnv,
    QuadcopterEnv,
    ground_effect_factor,
)

VEHICLES = (QuadcopterEnv, HelicopterEnv)
ENV_IDS = {QuadcopterEnv: "qtl/Quadcopter-v0", HelicopterEnv: "qtl/Helicopter-v0"}
TARGET = np.array([-1.0, -1.0, 1.5])
HOVER_HEIGHT = 3.0  # m, far above any ground effect
REACH_TOLERANCE = 0.2  # m
AUTOPILOT_SEEDS = (0, 1, 2)

vehicles = pytest.mark.parametrize("cls", VEHICLES, ids=lambda c: c.__name__)


def _hover_state(height: float = HOVER_HEIGHT) -> np.ndarray:
    state = np.zeros(12)
    state[2] = height
    return state


def _run(env: AircraftEnv, actions: np.ndarray) -> np.ndarray:
    """Noise-free states `T x 12` after each of the actions `T x 4`."""
    return np.array([env.step(a)[4]["state"] for a in actions])


def _hold(env: AircraftEnv, action: list[float], steps: int) -> np.ndarray:
    return _run(env, np.tile(np.asarray(action, dtype=float), (steps, 1)))


# ---- gymnasium conventions -------------------------------------------------------------------
@vehicles
# The observation is unbounded on purpose (positions, unwrapped angles); check_env warns about it.
@pytest.mark.filterwarnings("ignore:.*Box observation space m.*infinity:UserWarning")
def test_check_env(cls: type[AircraftEnv]) -> None:
    check_env(gymnasium.make(ENV_IDS[cls], render_mode="rgb_array").unwrapped)


@vehicles
def test_reset_is_deterministic(cls: type[AircraftEnv]) -> None:
    actions = np.random.default_rng(0).uniform(-1, 1, size=(30, 4))
    runs = []
    for seed in (7, 7, 8):
        env = cls(obs_noise_std=0.01)
        obs0, _ = env.reset(seed=seed)
        observations = [obs0] + [env.step(a)[0] for a in actions]
        runs.append(np.array(observations))
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.allclose(runs[0][0], runs[2][0])


@vehicles
def test_start_distribution_and_info(cls: type[AircraftEnv]) -> None:
    env = cls()
    assert env.start_mean.shape == env.start_std.shape == (12,)
    starts = np.array([env.reset(seed=s)[1]["state"] for s in range(200)])
    moving = env.start_std > 0
    np.testing.assert_array_equal(np.flatnonzero(moving), [0, 1, 5])  # x, y, yaw
    assert np.all(starts[:, ~moving] == 0.0)  # on the ground, level, at rest
    np.testing.assert_allclose(starts[:, moving].std(axis=0), env.start_std[moving], rtol=0.2)
    obs, info = env.reset(seed=0)
    np.testing.assert_array_equal(obs, info["state"])  # no observation noise by default
    assert obs.shape == (12,) and obs.dtype == np.float64
    assert info["actuators"].shape == (4,)  # hidden states, not in the observation


@vehicles
def test_truncation_at_horizon_and_no_termination(cls: type[AircraftEnv]) -> None:
    env = cls(horizon=5)
    env.reset(seed=0)
    flags = [env.step(np.ones(4))[2:4] for _ in range(5)]
    assert [t for t, _ in flags] == [False] * 5
    assert [t for _, t in flags] == [False] * 4 + [True]


@vehicles
def test_options_state_round_trip(cls: type[AircraftEnv]) -> None:
    state = np.array([0.3, -0.2, 1.1, 0.1, -0.2, 0.4, 0.5, -0.1, 0.2, 0.3, -0.4, 0.6])
    _, info = cls().reset(seed=0, options={"state": state})
    np.testing.assert_allclose(info["state"], state, atol=1e-12)


@vehicles
def test_make_passes_kwargs(cls: type[AircraftEnv]) -> None:
    env = gymnasium.make(ENV_IDS[cls], mass=1.7, horizon=3, reward_width=0.5).unwrapped
    assert isinstance(env, cls)
    assert (env.mass, env.horizon, env.reward_spec.width) == (1.7, 3, 0.5)


BAD_KWARGS = [
    ("mass", 0.0),
    ("mass", -1.0),
    ("dt", 0.0),
    ("integrator_dt", 0.2),  # > dt
    ("horizon", 0),
    ("horizon", 2.5),
    ("obs_noise_std", -0.1),
    ("rotor_radius", 0.0),
    ("inertia", (1.0, 1.0)),
    ("inertia", (1.0, -1.0, 1.0)),
    ("reward_width", 0.0),
    ("start_xy_std", -1.0),
    ("target", (1.0, 2.0)),
    ("max_thrust", float("nan")),
    ("ground_effect", "yes"),
    ("render_mode", "human"),
]
VEHICLE_BAD_KWARGS = [
    (QuadcopterEnv, "arm_length", -0.1),
    (QuadcopterEnv, "motor_time_constant", 0.0),
    (QuadcopterEnv, "drag_coefficient", (0.1, -0.1, 0.1)),
    (HelicopterEnv, "rotor_time_constant", 0.0),
    (HelicopterEnv, "tail_arm", -0.8),
    (HelicopterEnv, "rate_damping", (1.0, 1.0)),
]


@pytest.mark.parametrize(
    ("cls", "name", "value"),
    [(c, n, v) for c, (n, v) in itertools.product(VEHICLES, BAD_KWARGS)] + VEHICLE_BAD_KWARGS,
)
def test_bad_kwargs_raise(cls: type[AircraftEnv], name: str, value: object) -> None:
    with pytest.raises(ValueError, match=rf"^{name} must be .*got {re.escape(repr(value))}"):
        cls(**{name: value})


# ---- reward ------------------------------------------------------------------------------------
@vehicles
def test_reward_is_the_closed_form(cls: type[AircraftEnv]) -> None:
    env = cls()
    spec = env.reward_spec
    assert spec.angle_dims == () and spec.width == 0.25
    np.testing.assert_array_equal(np.diag(spec.weight), [1, 1, 1] + [0] * 9)
    rng = np.random.default_rng(1)
    for position in ([-1.0, -1.0, 1.5], [0.0, 0.0, 0.0], [-0.8, -1.1, 1.3], [1.0, 2.0, 3.0]):
        state = np.concatenate([position, rng.normal(size=9)])
        expected = math.exp(-np.sum((np.asarray(position) - TARGET) ** 2) / (2 * 0.25**2))
        assert spec(state) == pytest.approx(expected, rel=1e-12, abs=1e-300)
    # `step` scores the noise-free successor state with the same function.
    env.reset(seed=0, options={"state": np.r_[-0.9, -1.1, 1.4, np.zeros(9)]})
    _, reward, *_, info = env.step(np.zeros(4))
    d2 = np.sum((info["state"][:3] - TARGET) ** 2)
    assert reward == pytest.approx(math.exp(-d2 / (2 * 0.25**2)), rel=1e-12)


# ---- physics -----------------------------------------------------------------------------------
@vehicles
def test_more_collective_lifts(cls: type[AircraftEnv]) -> None:
    heights = []
    for collective in (0.1, 0.4, 0.7, 1.0):
        env = cls()
        env.reset(seed=0)
        heights.append(_hold(env, [collective, 0, 0, 0], 20)[-1, 2])
    assert heights[0] > 0.0
    assert np.all(np.diff(heights) > 0.1), heights


@vehicles
@pytest.mark.parametrize("collective", [-1.0, -0.5])
def test_low_collective_stays_on_the_ground(cls: type[AircraftEnv], collective: float) -> None:
    env = cls()
    _, info = env.reset(seed=3)
    start = info["state"]
    # Full attitude set-points on the ground: no tilting, sliding, yawing or sinking.
    states = _hold(env, [collective, 1.0, -1.0, 1.0], 30)
    np.testing.assert_array_equal(states, np.tile(start, (30, 1)))
    assert start[2] == 0.0


def test_ground_effect_factor() -> None:
    radius = 0.5
    assert ground_effect_factor(0.5 * radius, radius) == pytest.approx(4.0 / 3.0)
    assert ground_effect_factor(0.0, radius) == pytest.approx(4.0 / 3.0)  # clipped at R/2
    assert ground_effect_factor(radius, radius) == pytest.approx(1.0 / (1.0 - 1.0 / 16.0))
    assert 1.0 < ground_effect_factor(4.0 * radius, radius) < 1.005
    assert ground_effect_factor(100.0 * radius, radius) == pytest.approx(1.0, abs=1e-5)
    heights = np.linspace(0.0, 10.0 * radius, 101)
    factors = ground_effect_factor(heights, radius)
    assert factors.shape == heights.shape
    assert np.all(np.diff(factors) <= 0) and np.all((factors >= 1.0) & (factors <= 1.5))
    with pytest.raises(ValueError, match="rotor_radius"):
        ground_effect_factor(1.0, 0.0)


@vehicles
def test_ground_effect_in_the_dynamics(cls: type[AircraftEnv]) -> None:
    env = cls()
    radius = env.rotor_radius
    assert env.thrust_factor(0.0) > 1.2
    assert env.thrust_factor(4.0 * radius) < 1.005
    assert cls(ground_effect=False).thrust_factor(0.0) == 1.0
    # 90 % of the weight lifts the vehicle off in ground effect, but only into it: the
    # equilibrium rotor height is R / (4 √0.1) ≈ 0.8 R.
    collective = env.collective_for_thrust(0.9 * env.mass * GRAVITY)
    env.reset(seed=0)
    heights = _hold(env, [collective, 0, 0, 0], 50)[:, 2]
    assert heights.max() > 0.005
    assert heights.max() + env.rotor_height < 2.0 * radius
    no_effect = cls(ground_effect=False)
    no_effect.reset(seed=0)
    assert np.all(_hold(no_effect, [collective, 0, 0, 0], 50)[:, 2] == 0.0)


@vehicles
def test_attitude_setpoints_move_the_vehicle(cls: type[AircraftEnv]) -> None:
    """Positive pitch flies towards +x, positive roll towards −y; the yaw set-point is tracked."""
    env = cls()
    for action, axis, sign in (([0, 0, 1, 0], 0, 1.0), ([0, 1, 0, 0], 1, -1.0)):
        env.reset(seed=0, options={"state": _hover_state()})
        velocity = _hold(env, action, 15)[-1, 6 + axis]
        assert sign * velocity > 1.0
    env.reset(seed=0, options={"state": _hover_state()})
    yaw = _hold(env, [0, 0, 0, 0.5], 30)[-1, 5]
    assert yaw == pytest.approx(0.25 * math.pi, abs=0.15)


def test_the_vehicles_differ() -> None:
    actions = np.random.default_rng(0).uniform(-0.2, 0.6, size=(40, 4))
    runs = []
    for cls in VEHICLES:
        env = cls()
        env.reset(seed=0)
        runs.append(_run(env, actions))
    assert np.abs(runs[0] - runs[1]).max() > 0.5


def test_only_the_helicopter_has_yaw_coupling_and_lateral_bias() -> None:
    quad, heli = QuadcopterEnv(), HelicopterEnv()
    assert quad.trim_roll == 0.0 and heli.trim_roll < -0.03
    for env, coupled in ((quad, False), (heli, True)):
        # More collective, yaw set-point 0: the helicopter's main-rotor torque turns it.
        env.reset(seed=0, options={"state": _hover_state()})
        final = _hold(env, [0.5, 0, 0, 0], 10)[-1]
        assert (abs(final[5]) > 0.05) == coupled
        # Level, yaw held: the tail-rotor side force pushes the helicopter sideways (−y).
        env.reset(seed=0, options={"state": _hover_state()})
        final = _hold(env, [env.collective_for_thrust(env.mass * GRAVITY), 0, 0, 0], 10)[-1]
        assert (final[7] < -0.2) == coupled


# ---- autopilot ---------------------------------------------------------------------------------
@vehicles
@pytest.mark.parametrize("seed", AUTOPILOT_SEEDS)
def test_autopilot_reaches_the_target(cls: type[AircraftEnv], seed: int) -> None:
    env = gymnasium.make(ENV_IDS[cls])
    autopilot = Autopilot(env)
    obs, _ = env.reset(seed=seed)
    distances, truncated = [], False
    while not truncated:
        action = autopilot(obs)
        np.testing.assert_array_equal(action, env.unwrapped.autopilot(obs))
        obs, _, terminated, truncated, info = env.step(action)
        assert not terminated
        distances.append(np.linalg.norm(info["state"][:3] - TARGET))
    assert len(distances) == 200
    # Within 0.2 m well before the end, and held there for the last 10 s.
    assert max(distances[100:]) < REACH_TOLERANCE, min(distances)


def test_autopilot_rejects_other_envs() -> None:
    with pytest.raises(ValueError, match="env must be"):
        Autopilot(gymnasium.make("Pendulum-v1"))


# ---- rendering ---------------------------------------------------------------------------------
@vehicles
def test_render_rgb_array(cls: type[AircraftEnv]) -> None:
    env = cls(render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint8
    env.step(np.array([1.0, 0.5, 0.5, 0.0]))
    env.step(np.array([1.0, 0.5, 0.5, 0.0]))
    assert not np.array_equal(env.render(), frame)  # the vehicle moved
    with pytest.warns(UserWarning, match="render_mode"):
        assert cls().render() is None  # no render_mode
