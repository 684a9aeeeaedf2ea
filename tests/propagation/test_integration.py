"""Speed integration: the linear step and its covariance, and particles that integrate positions from velocities."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from qtl.build import build
from qtl.errors import TaskError, UserError
from qtl.features import AngleFeatures
from qtl.gaussian import Gaussian
from qtl.models import GPPosteriorCache
from qtl.propagation import Particles
from qtl.propagation.integration import SpeedIntegration
from qtl.propagation.pathwise import MatheronPaths
from qtl.task import Kinematics
from tests.helpers import gradcheck_value_wrt_policy_and_start, squashed_rbf_parts, tiny_config
from tests.propagation.reference import assert_marginal_paths

DTYPE = torch.float64
# Agreement with an independent per-particle reference using the same random numbers.
EXACT_RTOL, EXACT_ATOL = 1e-9, 1e-12
# A cart-pole-like layout: x, ẋ, θ (an angle), θ̇; positions x and θ, their velocities ẋ and θ̇.
CARTPOLE = Kinematics(positions=(0, 2), velocities=(1, 3), period=0.1)
MODELLED = [1, 3]
# A period long enough that a position's share (T/2)² v of its velocity's variance is seen by the reward.
LONG_PERIOD = CARTPOLE._replace(period=1.5)


def cartpole_parts(gp_factory, num_basis: int = 6):
    """A 4-D state with an angle at 2, a squashed RBF policy, a quadratic reward."""
    return squashed_rbf_parts(gp_factory, 4, (2,), num_basis, seeds=(31, 32))


def speed(gp, policy, reward, **kwargs) -> Particles:
    """Particles with speed integration on the cart-pole-like parts."""
    settings = {"num_particles": 16, "seed": 3, "integration": "speed", "kinematics": CARTPOLE} | kwargs
    return Particles(gp, policy, reward, angle_dims=(2,), **settings)


def start() -> Gaussian:
    """A start distribution of the cart-pole-like state."""
    return Gaussian(torch.tensor([0.1, -0.2, 2.5, 0.3], dtype=DTYPE),
                    torch.diag(torch.tensor([0.04, 0.09, 0.2, 0.1], dtype=DTYPE)))


def trapezoid(x: Tensor, delta: Tensor, kinematics: Kinematics = CARTPOLE) -> Tensor:
    """The step written out: other dims + Δ, positions q + T q̇ + (T/2) Δq̇ (``delta`` `... x D`)."""
    out = x + delta
    for p, v in zip(kinematics.positions, kinematics.velocities, strict=True):
        out[..., p] = x[..., p] + kinematics.period * x[..., v] + 0.5 * kinematics.period * delta[..., v]
    return out


def test_step_is_the_trapezoid_rule_and_leaves_other_dims_to_their_draws():
    # Five dimensions: positions 0 and 3, velocities 4 and 1, dimension 2 neither (x + Δ).
    integration = SpeedIntegration(5, Kinematics((0, 3), (4, 1), 0.05))
    assert integration.outputs == (1, 2, 4)
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(7, 5, generator=gen, dtype=DTYPE)
    delta = torch.randn(7, 3, generator=gen, dtype=DTYPE)
    full = torch.zeros(7, 5, dtype=DTYPE)
    full[:, [1, 2, 4]] = delta
    expected = trapezoid(x, full, Kinematics((0, 3), (4, 1), 0.05))
    torch.testing.assert_close(integration.step(x, delta), expected, rtol=1e-14, atol=1e-14)
    # Equivalently q_{t+1} = q_t + T (q̇_t + q̇_{t+1}) / 2.
    nxt = integration.step(x, delta)
    torch.testing.assert_close(nxt[:, 0] - x[:, 0], 0.025 * (x[:, 4] + nxt[:, 4]), rtol=1e-13, atol=1e-14)


def test_covariance_is_that_of_the_stepped_draws(mc):
    # Δ ~ N(m, diag v) independent per output: the state's covariance is Jᵀ diag(v) J (Monte Carlo, 5 SE).
    integration = SpeedIntegration(4, CARTPOLE._replace(period=0.3))
    variance = torch.tensor([0.5, 2.0], dtype=DTYPE)
    gen = torch.Generator().manual_seed(1)
    draws = torch.randn(200_000, 2, generator=gen, dtype=DTYPE) * variance.sqrt()
    x = torch.tensor([0.3, -1.0, 2.0, 0.5], dtype=DTYPE)
    stepped = integration.step(x, draws)
    centred = stepped - stepped.mean(0)
    cov = integration.covariance(variance)
    mc.assert_mean(cov, centred[:, :, None] * centred[:, None, :], "state covariance")
    mc.assert_mean(integration.step(x, torch.zeros(2, dtype=DTYPE)), stepped, "state mean")


def test_weight_one_is_semi_implicit_euler_and_n_of_its_steps_are_weight_n_plus_one_over_2n():
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(9, 2, generator=gen, dtype=DTYPE)
    delta = torch.randn(9, 1, generator=gen, dtype=DTYPE)
    # w = 1: q_{t+1} = q_t + T q̇_{t+1}, semi-implicit Euler.
    nxt = SpeedIntegration(2, Kinematics((0,), (1,), 1.0, 1.0)).step(x, delta)
    torch.testing.assert_close(nxt[:, 1], x[:, 1] + delta[:, 0], rtol=0, atol=0)
    torch.testing.assert_close(nxt[:, 0], x[:, 0] + nxt[:, 1], rtol=1e-15, atol=1e-15)
    # n = 5 semi-implicit Euler steps of one time unit with equal increments Δq̇/5 (the mountain car's decision):
    # T = 5, w = (n + 1)/(2n) = 0.6.
    q, v = x[:, 0].clone(), x[:, 1].clone()
    for _ in range(5):
        v = v + delta[:, 0] / 5
        q = q + v
    nxt = SpeedIntegration(2, Kinematics((0,), (1,), 5.0, 0.6)).step(x, delta)
    torch.testing.assert_close(nxt, torch.stack([q, v], dim=-1), rtol=1e-13, atol=1e-13)


def test_a_weight_outside_zero_one_is_a_task_error():
    with pytest.raises(TaskError, match=r"task\.kinematics\.weight must be in \[0, 1\]"):
        SpeedIntegration(4, Kinematics((0, 2), (1, 3), 0.1, 1.5))


@pytest.mark.parametrize(("positions", "velocities", "period"), [
    ((0, 2), (1,), 0.1),  # unpaired
    ((0, 1), (1, 3), 0.1),  # a velocity that is also a position
    ((0, 2), (1, 4), 0.1),  # out of range
    ((0, 2), (1, 3), 0.0),  # no period
    ((), (), 0.1),  # nothing to integrate
])
def test_bad_kinematics_are_task_errors(positions, velocities, period):
    with pytest.raises(TaskError, match=r"task\.kinematics"):
        SpeedIntegration(4, Kinematics(positions, velocities, period))


@pytest.mark.parametrize("include_noise", [False, True])
def test_marginal_particles_integrate_positions_from_their_velocity_draws(gp_factory, posterior, include_noise):
    # An independent reference: the GP's predictive at each particle for the velocities only, drawn with the
    # propagator's own noise columns, and the positions by the trapezoid rule.
    gp, policy, reward = cartpole_parts(gp_factory)
    particles = speed(gp, policy, reward, include_noise=include_noise)

    def step(x: Tensor, delta: Tensor) -> Tensor:  # the velocities' draws, the positions by the trapezoid rule
        modelled = torch.zeros_like(x)
        modelled[:, MODELLED] = delta[:, MODELLED]
        return trapezoid(x, modelled)

    assert_marginal_paths(particles, gp, policy, start(), 4, posterior, include_noise, step)


def reference_functions(cache: GPPosteriorCache, paths: MatheronPaths, z: Tensor, outputs: list[int]) -> Tensor:
    """The drawn functions of ``outputs`` at ``z`` `P x D_in` written out: `P x E'` (prior features + data update)."""
    theta = cache.hyperparameters
    ls = theta.lengthscales[outputs]  # E' x D_in
    angle = torch.einsum("pd,eld->epl", z, paths.frequencies / ls[:, None, :]) + paths.phases[:, None, :]
    prior = (paths.weights * torch.cos(angle)).sum(-1)  # E' x P
    sq = ((z / ls[:, None, :])[:, :, None, :] - (cache.inputs / ls[:, None, :])[:, None, :, :]).square().sum(-1)
    kernel = theta.signal_variance[outputs][:, None, None] * torch.exp(-0.5 * sq)  # E' x P x n
    return (prior + (kernel * paths.update).sum(-1)).T


@pytest.mark.parametrize("include_noise", [False, True])
def test_pathwise_particles_integrate_positions_from_their_own_velocity_functions(gp_factory, include_noise):
    # One function per particle for the velocities only (E' = 2 drawn outputs); positions by the trapezoid rule.
    gp, policy, reward = cartpole_parts(gp_factory)
    particles = speed(gp, policy, reward, include_noise=include_noise, sampling="pathwise", num_features=64)
    horizon = 4
    cache = gp.posterior_cache()
    with torch.no_grad():
        states, _ = particles.trajectories(start(), horizon)
        start_noise, step_noise, _ = particles.base_noise(horizon)
        paths = particles.functions()
        assert paths.update.shape[-3] == len(MODELLED)
        features = AngleFeatures(4, (2,))
        x = start().mean + start_noise @ torch.linalg.cholesky(start().cov).mT
        expected = [x]
        for _ in range(horizon):
            z = torch.cat([features(x), policy(features(x))], dim=-1)
            draw = reference_functions(cache, paths, z, MODELLED)
            if include_noise:
                draw = draw + cache.hyperparameters.noise_variance[MODELLED].sqrt() * step_noise[_][:, MODELLED]
            delta = torch.zeros_like(x)
            delta[:, MODELLED] = draw
            x = trapezoid(x, delta)
            expected.append(x)
    torch.testing.assert_close(states, torch.stack(expected, dim=1), rtol=EXACT_RTOL, atol=EXACT_ATOL)


@pytest.mark.parametrize("sampling", ["marginal", "pathwise"])
def test_expected_reward_scores_the_gaussian_of_the_drawn_step(gp_factory, mc, sampling):
    # With expected_reward a step is scored under N(x A + m J, Jᵀ diag(v) J) per particle: the drawn successor's
    # residual x_1 − (x A + m J) has mean 0 and covariance Jᵀ diag(v) J (Monte Carlo, 5 SE). T = 1.5 s so that
    # the positions' share (T/2)² v is well above the Monte Carlo error.
    gp, policy, reward = cartpole_parts(gp_factory)
    particles = speed(gp, policy, reward, num_particles=50_000, expected_reward=True, sampling=sampling,
                      num_features=64, seed=5, kinematics=LONG_PERIOD)
    with torch.no_grad():
        states, _, predictive = particles._paths(start(), 1, None)
    residual = states[:, 1] - predictive.mean[:, 0]
    cov = predictive.cov[:, 0]
    assert cov[:, 0, 0].min() > 1e-4  # the positions do carry variance
    mc.assert_mean(torch.zeros(4, dtype=DTYPE), residual, "residual mean")
    mc.assert_mean(torch.zeros(4, 4, dtype=DTYPE), residual[:, :, None] * residual[:, None, :] - cov, "residual cov")
    # The value is the expected reward of those Gaussians.
    torch.testing.assert_close(particles.rollout(start(), 1).value, reward.expected(predictive).sum(-1).mean())


@pytest.mark.parametrize(("sampling", "expected_reward"), [("marginal", False), ("marginal", True),
                                                           ("pathwise", False)])
def test_gradcheck_speed_integrated_rollout(gp_factory, sampling, expected_reward):
    gp, policy, reward = cartpole_parts(gp_factory, num_basis=3)
    particles = speed(gp, policy, reward, num_particles=6, sampling=sampling, num_features=16,
                      expected_reward=expected_reward, seed=2)
    near = Gaussian(start().mean, 0.02 * torch.eye(4, dtype=DTYPE))
    assert gradcheck_value_wrt_policy_and_start(policy, lambda s: particles.rollout(s, 2).value, near)


def test_same_seed_same_rollout_and_delta_integration_is_unchanged(gp_factory):
    gp, policy, reward = cartpole_parts(gp_factory)
    first = speed(gp, policy, reward).rollout(start(), 3).value
    torch.testing.assert_close(speed(gp, policy, reward).rollout(start(), 3).value, first, rtol=0, atol=0)
    plain = Particles(gp, policy, reward, angle_dims=(2,), num_particles=16, seed=3)
    delta = Particles(gp, policy, reward, angle_dims=(2,), num_particles=16, seed=3, integration="delta",
                      kinematics=CARTPOLE)
    torch.testing.assert_close(delta.rollout(start(), 3).value, plain.rollout(start(), 3).value, rtol=0, atol=0)
    assert not torch.equal(first, plain.rollout(start(), 3).value)


def test_speed_integration_needs_kinematics_and_a_known_name(gp_factory):
    gp, policy, reward = cartpole_parts(gp_factory)
    with pytest.raises(UserError, match="needs the task's kinematics"):
        Particles(gp, policy, reward, angle_dims=(2,), integration="speed")
    with pytest.raises(UserError, match=r"propagation\.integration must be one of delta, speed"):
        Particles(gp, policy, reward, angle_dims=(2,), integration="euler", kinematics=CARTPOLE)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [(("task=pendulum", "propagation.integration=speed"), "task pendulum declares no kinematics"),
     (("propagation.integration=euler",), "propagation.integration must be one of delta, speed")],
)
def test_build_refuses_speed_integration_it_cannot_do_before_any_work(overrides, message):
    with pytest.raises(UserError, match=message):
        build(tiny_config("propagation=particles", *overrides))


def test_build_binds_the_tasks_kinematics_to_the_propagator(gp_factory):
    parts = build(tiny_config("propagation=particles", "propagation.integration=speed"))
    assert parts.task.kinematics == Kinematics((0, 2), (1, 3), 0.1)  # cart-pole, its env's dt
    gp, policy, reward = cartpole_parts(gp_factory)
    particles = parts.make_propagator(gp, policy, reward, angle_dims=(2,))
    assert particles.integration.outputs == (1, 3) and particles.integration.period == 0.1
