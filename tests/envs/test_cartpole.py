"""Tests of the cart-pole swing-up: gymnasium API, physics, reward, kwargs."""

from __future__ import annotations

import math
import warnings

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import qtl.envs  # noqa: F401  (registers the ids)
from qtl.envs.cartpole import CartPoleSwingUpEnv
from qtl.envs.rewards import SaturatingReward

ENV_ID = "qtl/CartPoleSwingUp-v0"
# A non-trivial start: pole past horizontal, cart and pole moving.
SWINGING_STATE = np.array([0.1, 0.5, 2.0, 1.0])
# Energy drift bound with b = 0, u = 0 over 10 s (RK4 at 0.01 s measures ~1.2e-5).
ENERGY_DRIFT_BOUND = 1e-4
# check_env warns about infinite Box bounds; the cart track and the unwrapped angle are
# unbounded by design, so these two warnings (and only these) are expected.
EXPECTED_CHECK_ENV_WARNINGS = ("minimum value is -infinity", "maximum value is infinity")


def tip_distance_sq(state: np.ndarray, ell: float) -> np.ndarray:
    """TASKS.md's closed form d² = x² + 2 x l sin θ + 2 l² + 2 l² cos θ (`... x 4` states)."""
    x, th = state[..., 0], state[..., 2]
    return x**2 + 2 * x * ell * np.sin(th) + 2 * ell**2 + 2 * ell**2 * np.cos(th)


def rollout(env: gymnasium.Env, actions: np.ndarray, seed: int | None) -> np.ndarray:
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for a in actions:
        obs, *_ = env.step(np.array([a]))
        out.append(obs)
    return np.array(out)


def momentum(env: CartPoleSwingUpEnv, s: np.ndarray) -> float:
    """Horizontal momentum (M+m) ẋ + m (l/2) θ̇ cos θ, conserved when b = 0 and u = 0."""
    m_tot = env.cart_mass + env.pole_mass
    return m_tot * s[1] + 0.5 * env.pole_mass * env.pole_length * s[3] * math.cos(s[2])


# ---- gymnasium API ----------------------------------------------------------------------------
@pytest.mark.parametrize("render_mode", [None, "rgb_array"])
def test_check_env(render_mode: str | None) -> None:
    env = gymnasium.make(ENV_ID, render_mode=render_mode)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
    unexpected = [str(w.message) for w in caught if not any(s in str(w.message) for s in EXPECTED_CHECK_ENV_WARNINGS)]
    assert not unexpected


def test_spaces_and_no_time_limit_wrapper() -> None:
    env = gymnasium.make(ENV_ID)
    assert env.spec is not None and env.spec.max_episode_steps is None
    assert env.observation_space.shape == (4,) and env.observation_space.dtype == np.float64
    assert env.action_space.shape == (1,)
    np.testing.assert_array_equal(env.action_space.low, [-1.0])
    np.testing.assert_array_equal(env.action_space.high, [1.0])


def test_reset_determinism() -> None:
    env = CartPoleSwingUpEnv(obs_noise_std=0.01)
    actions = np.random.default_rng(0).uniform(-1, 1, size=20)
    a = rollout(env, actions, seed=7)
    b = rollout(env, actions, seed=7)
    c = rollout(env, actions, seed=8)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_start_distribution_attributes() -> None:
    env = CartPoleSwingUpEnv(start_std=0.1)
    np.testing.assert_array_equal(env.start_mean, np.zeros(4))
    np.testing.assert_array_equal(env.start_std, np.full(4, 0.1))
    env.reset(seed=0)
    starts = np.array([env.reset()[1]["state"] for _ in range(4000)])
    np.testing.assert_allclose(starts.mean(0), env.start_mean, atol=0.01)
    np.testing.assert_allclose(starts.std(0), env.start_std, rtol=0.05)
    per_dim = CartPoleSwingUpEnv(start_std=(0.1, 0.0, 0.2, 0.0))
    np.testing.assert_array_equal(per_dim.start_std, [0.1, 0.0, 0.2, 0.0])


def test_truncation_termination_and_info_state() -> None:
    env = CartPoleSwingUpEnv(horizon=7, obs_noise_std=0.01)
    obs, info = env.reset(seed=3)
    assert not np.array_equal(obs, info["state"])  # noisy observation, noise-free state
    for t in range(1, 8):
        obs, reward, terminated, truncated, info = env.step(np.array([0.3]))
        assert terminated is False
        assert truncated is (t == 7)
        np.testing.assert_array_equal(info["state"], env.state)
        assert info["state"] is not env.state  # a copy
        assert 0.0 < np.abs(obs - info["state"]).max() < 0.1
        # The reward scores the noise-free successor state.
        assert reward == env.reward_spec(info["state"])


def test_step_before_reset_raises() -> None:
    with pytest.raises(gymnasium.error.ResetNeeded):
        CartPoleSwingUpEnv().step(np.zeros(1))


def test_action_is_clipped_and_scaled() -> None:
    def first_step(action: float, **kwargs: float) -> np.ndarray:
        env = CartPoleSwingUpEnv(**kwargs)
        env.reset(options={"state": np.zeros(4)})
        return env.step(np.array([action]))[4]["state"]

    np.testing.assert_array_equal(first_step(5.0), first_step(1.0))
    np.testing.assert_array_equal(first_step(-5.0), first_step(-1.0))
    # Pushing right from rest moves the cart right and swings the pole back (θ < 0).
    pushed = first_step(1.0)
    assert pushed[0] > 0 and pushed[1] > 0 and pushed[2] < 0
    # The action is a fraction of max_force: half the action at twice the force is the same.
    np.testing.assert_allclose(first_step(0.5, max_force=20.0), first_step(1.0), rtol=1e-12)


def test_reset_from_given_state() -> None:
    env = CartPoleSwingUpEnv()
    obs, _ = env.reset(seed=0, options={"state": SWINGING_STATE})
    np.testing.assert_array_equal(obs, SWINGING_STATE)
    with pytest.raises(ValueError, match="state"):
        env.reset(options={"state": [0.0, 1.0]})


# ---- physics ----------------------------------------------------------------------------------
def test_energy_expression_matches_rigid_body_energy() -> None:
    """E of TASKS.md (θ = 0 down) = cart KE + rod KE (about its centre) + rod PE, by hand."""
    env = CartPoleSwingUpEnv()
    big_m, m, ell, g = env.cart_mass, env.pole_mass, env.pole_length, env.gravity
    for x, xd, th, thd in np.random.default_rng(1).normal(size=(20, 4)) * 2:
        com_v = np.array([xd + 0.5 * ell * math.cos(th) * thd, 0.5 * ell * math.sin(th) * thd])
        kinetic = 0.5 * big_m * xd**2 + 0.5 * m * com_v @ com_v + 0.5 * (m * ell**2 / 12) * thd**2
        potential = m * g * (-0.5 * ell * math.cos(th))  # centre of mass at height −(l/2) cos θ
        assert env.energy(np.array([x, xd, th, thd])) == pytest.approx(kinetic + potential)


def test_energy_and_momentum_conserved_without_friction() -> None:
    env = CartPoleSwingUpEnv(friction=0.0)
    env.reset(options={"state": SWINGING_STATE})
    e0, p0 = env.energy(), momentum(env, env.state)
    drift_e, drift_p, angles = 0.0, 0.0, []
    for _ in range(100):  # 10 s
        env.step(np.zeros(1))
        drift_e = max(drift_e, abs(env.energy() - e0))
        drift_p = max(drift_p, abs(momentum(env, env.state) - p0))
        angles.append(env.state[2])
    assert np.ptp(angles) > math.pi  # the motion is far from trivial (the pole goes over the top)
    assert drift_e / abs(e0) < ENERGY_DRIFT_BOUND
    assert drift_p / abs(p0) < ENERGY_DRIFT_BOUND


def test_integrator_converges_at_fourth_order() -> None:
    def drift(integrator_dt: float) -> float:
        env = CartPoleSwingUpEnv(friction=0.0, integrator_dt=integrator_dt)
        env.reset(options={"state": SWINGING_STATE})
        e0 = env.energy()
        for _ in range(30):
            env.step(np.zeros(1))
        return abs(env.energy() - e0)

    # RK4 is 4th order: halving the sub-step must cut the drift by far more than 2×.
    assert drift(0.02) / drift(0.01) > 8.0


def test_friction_dissipates_energy() -> None:
    env = CartPoleSwingUpEnv(friction=0.5)
    env.reset(options={"state": SWINGING_STATE})
    energies = [env.energy()]
    for _ in range(50):
        env.step(np.zeros(1))
        energies.append(env.energy())
    # dE/dt = −b ẋ² ≤ 0, up to the integrator's error.
    assert np.all(np.diff(energies) <= 1e-6)
    assert energies[-1] < energies[0] - 0.1


def test_hanging_down_is_stable_and_upright_is_unstable() -> None:
    env = CartPoleSwingUpEnv()
    env.reset(options={"state": [0.0, 0.0, 0.1, 0.0]})
    down = [env.step(np.zeros(1))[4]["state"][2] for _ in range(50)]
    assert np.max(np.abs(down)) <= 0.1 + 1e-9
    env.reset(options={"state": [0.0, 0.0, math.pi - 0.01, 0.0]})
    up = [env.step(np.zeros(1))[4]["state"][2] for _ in range(50)]
    assert np.max(np.abs(np.array(up) - math.pi)) > 1.0


def test_pole_mass_kwarg_through_make_changes_dynamics() -> None:
    heavy = gymnasium.make(ENV_ID, pole_mass=2.0)
    light = gymnasium.make(ENV_ID)
    assert heavy.unwrapped.pole_mass == 2.0 and light.unwrapped.pole_mass == 0.5
    actions = np.random.default_rng(0).uniform(-1, 1, size=10)
    a, b = rollout(heavy, actions, seed=0), rollout(light, actions, seed=0)
    np.testing.assert_array_equal(a[0], b[0])  # same start
    assert np.abs(a[1:] - b[1:]).max() > 0.1


# ---- reward -----------------------------------------------------------------------------------
def test_reward_spec_is_the_declarative_tip_distance() -> None:
    env = CartPoleSwingUpEnv()
    spec = env.reward_spec
    assert isinstance(spec, SaturatingReward)
    assert spec.angle_dims == (2,) and spec.width == 0.25
    np.testing.assert_array_equal(spec.target, [0, 0, 0, 0, -1])
    states = np.random.default_rng(2).normal(size=(500, 4)) * [1.0, 2.0, 3.0, 5.0]
    expected = np.exp(-tip_distance_sq(states, 0.6) / (2 * 0.25**2))
    np.testing.assert_allclose(spec(states), expected, rtol=1e-10, atol=1e-300)


@pytest.mark.parametrize("pole_length", [0.6, 0.5])
def test_step_reward_equals_closed_form(pole_length: float) -> None:
    env = CartPoleSwingUpEnv(pole_length=pole_length)
    env.reset(seed=4, options={"state": [0.2, 0.0, 2.6, 0.0]})
    for a in np.random.default_rng(4).uniform(-1, 1, size=15):
        _, reward, _, _, info = env.step(np.array([a]))
        d2 = tip_distance_sq(info["state"], pole_length)
        assert reward == pytest.approx(math.exp(-d2 / (2 * 0.25**2)), rel=1e-12)


def test_reward_extremes() -> None:
    env = CartPoleSwingUpEnv()
    assert env.reward_spec(np.array([0.0, 0.0, math.pi, 0.0])) == pytest.approx(1.0)
    # Velocities do not enter the tip distance.
    assert env.reward_spec(np.array([0.0, 3.0, -math.pi, 4.0])) == pytest.approx(1.0)
    assert env.reward_spec(np.zeros(4)) < 1e-4  # hanging down: d = 2l
    assert env.reward_spec(np.array([0.6, 0.0, math.pi, 0.0])) < 0.06  # 0.6 m off: "close to 0"


def test_literal_reward_reading_is_an_option() -> None:
    # TASKS.md: the literal exp(−0.125 d²) = reward_width 2 scores 0.83 hanging down.
    env = CartPoleSwingUpEnv(reward_width=2.0)
    assert env.reward_spec(np.zeros(4)) == pytest.approx(math.exp(-0.125 * 4 * 0.36))


# ---- track limit ------------------------------------------------------------------------------
def test_check_env_with_a_track_limit() -> None:
    env = gymnasium.make(ENV_ID, track_limit=0.5)
    assert env.unwrapped.track_limit == 0.5
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
    unexpected = [str(w.message) for w in caught if not any(s in str(w.message) for s in EXPECTED_CHECK_ENV_WARNINGS)]
    assert not unexpected


@pytest.mark.parametrize(("limit", "push"), [(0.5, 1.0), (0.5, -1.0), (0.3, 0.6)])
def test_track_limit_terminates_exactly_when_the_cart_leaves_the_track(limit: float, push: float) -> None:
    env = CartPoleSwingUpEnv(track_limit=limit, obs_noise_std=0.01)
    assert env.track_limit == limit
    env.reset(seed=0)
    for _ in range(env.horizon):
        _, reward, terminated, truncated, info = env.step(np.array([push]))
        assert terminated is bool(abs(info["state"][0]) > limit)  # the noise-free state decides
        assert reward == env.reward_spec(info["state"])
        if terminated:
            break
    assert terminated and not truncated  # a steady push runs the cart off its track within the episode


def test_track_limit_on_the_bound_does_not_terminate() -> None:
    env = CartPoleSwingUpEnv(track_limit=0.5, horizon=1)
    env.reset(options={"state": [0.5, 0.0, 0.0, 0.0]})  # at rest on the bound: |x| = 0.5 is not > 0.5
    *_, terminated, truncated, info = env.step(np.array([0.0]))
    assert info["state"][0] == pytest.approx(0.5) and terminated is False and truncated is True


def test_default_track_is_unbounded_and_the_dynamics_unchanged() -> None:
    actions = np.random.default_rng(1).uniform(-1, 1, size=50)

    def episode(env: CartPoleSwingUpEnv) -> tuple[np.ndarray, list[float], list[bool]]:
        obs, _ = env.reset(seed=4)
        observations, rewards, ends = [obs], [], []
        for a in actions:
            obs, reward, terminated, truncated, _ = env.step(np.array([a]))
            observations.append(obs)
            rewards.append(reward)
            ends.append((terminated, truncated))
        return np.array(observations), rewards, ends

    default = episode(CartPoleSwingUpEnv(obs_noise_std=0.01))
    assert CartPoleSwingUpEnv().track_limit is None
    assert np.abs(default[0][:, 0]).max() > 1.0  # random pushes leave any short track
    for other in (CartPoleSwingUpEnv(obs_noise_std=0.01, track_limit=None),
                  CartPoleSwingUpEnv(obs_noise_std=0.01, track_limit=1e6)):
        observations, rewards, ends = episode(other)
        np.testing.assert_array_equal(observations, default[0])
        assert rewards == default[1] and ends == default[2]
    assert [end for end, _ in default[2]] == [False] * len(actions)


def test_render_marks_the_track_ends() -> None:
    frames = []
    for limit in (None, 0.5):
        env = CartPoleSwingUpEnv(render_mode="rgb_array", track_limit=limit)
        env.reset(options={"state": [0.0, 0.0, 0.0, 0.0]})
        frames.append(env.render())
    assert frames[0].shape == frames[1].shape and np.any(frames[0] != frames[1])


# ---- kwargs -----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("cart_mass", 0.0),
        ("pole_mass", -0.5),
        ("pole_length", 0.0),
        ("friction", -0.1),
        ("gravity", -9.82),
        ("max_force", 0.0),
        ("dt", 0.0),
        ("dt", -0.1),
        ("integrator_dt", 0.0),
        ("integrator_dt", 0.2),
        ("horizon", 0),
        ("horizon", 2.5),
        ("horizon", True),
        ("start_std", -0.1),
        ("start_std", (0.1, 0.1)),
        ("obs_noise_std", -0.01),
        ("reward_width", 0.0),
        ("pole_mass", float("nan")),
        ("pole_mass", "heavy"),
        ("render_mode", "human"),
        ("track_limit", 0.0),
        ("track_limit", -0.5),
        ("track_limit", float("inf")),
        ("track_limit", "short"),
    ],
)
def test_bad_kwargs_raise(name: str, value: object) -> None:
    with pytest.raises(ValueError, match=name):
        CartPoleSwingUpEnv(**{name: value})


def test_integrator_dt_splits_dt_evenly() -> None:
    env = CartPoleSwingUpEnv(dt=0.1, integrator_dt=0.03)
    assert env.n_substeps == 4 and env.integrator_dt == pytest.approx(0.025)
    assert CartPoleSwingUpEnv().n_substeps == 10


# ---- rendering --------------------------------------------------------------------------------
def test_render_rgb_array() -> None:
    env = CartPoleSwingUpEnv(render_mode="rgb_array")
    env.reset(seed=0)
    down = env.render()
    assert down is not None and down.dtype == np.uint8 and down.ndim == 3 and down.shape[2] == 3
    env.reset(options={"state": [0.0, 0.0, math.pi, 0.0]})
    up = env.render()
    assert up is not None and up.shape == down.shape and np.any(up != down)
    env.reset(options={"state": [10.0, 0.0, 1.0, 0.0]})  # far down the track: view follows
    far = env.render()
    assert far is not None and far.shape == down.shape


def test_render_without_mode_warns() -> None:
    env = CartPoleSwingUpEnv()
    env.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert env.render() is None
