"""Particles: one step against moment matching, exact per-particle dynamics, common random numbers, guards."""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate

from qtl.config import register_configs
from qtl.errors import NonFiniteObjective, UserError
from qtl.gaussian import Gaussian
from qtl.policies import LinearPolicy, RBFPolicy, SquashedPolicy
from qtl.propagation import MomentMatching, Particles
from qtl.propagation.objective import SearchReward
from qtl.propagation.resampling import gaussian_resample as _gaussian_resample
from qtl.propagation.samplers import safe_sqrt as _safe_sqrt
from qtl.rewards import AngleDistanceReward
from tests.helpers import gradcheck_value_wrt_policy_and_start, quadratic_reward, squashed_rbf_parts
from tests.propagation.reference import assert_marginal_paths
from tests.propagation.restarts import assert_restarts_equal_separate

DTYPE = torch.float64
# Enough particles that the Monte Carlo standard error of one step is small against the
# moments; the acceptance rule is the shared one (conftest `mc`: within 5 standard errors,
# each estimated from the per-particle terms as std/√P).
MANY_PARTICLES = 100_000
# Where moment matching is an approximation (angles, a squashed RBF policy): mean error in units
# of the particles' standard deviation, and the ratio of predicted to particle standard deviation.
APPROX_MEAN_TOL = 0.15
APPROX_STD_RATIO = (0.75, 1.25)
# Agreement of particles with an independent per-particle reference using the same noise.
EXACT_RTOL, EXACT_ATOL = 1e-9, 1e-12


def linear_parts(gp_factory):
    """No angles, a linear policy: moment matching is exact for one step."""
    gp = gp_factory(40, 2, 1, seed=21)
    policy = LinearPolicy(2, 1, weight=torch.tensor([[0.8, -0.5]], dtype=DTYPE), bias=torch.tensor([0.2], dtype=DTYPE))
    return gp, policy, quadratic_reward(2)


def pendulum_parts(gp_factory, num_basis: int = 8):
    """A 3-D state with an angle, a squashed RBF policy: PILCO's full configuration."""
    return squashed_rbf_parts(gp_factory, 3, (1,), num_basis, seeds=(22, 23))


@pytest.mark.parametrize("include_noise", [False, True])
def test_one_step_converges_to_exact_moment_matching(gp_factory, mc, include_noise):
    # No angles and a linear policy: [x, u] is Gaussian and moment matching's step is exact,
    # so the particle moments must agree with it within their Monte Carlo standard error.
    gp, policy, reward = linear_parts(gp_factory)
    start = Gaussian(torch.tensor([0.3, -0.4], dtype=DTYPE), torch.tensor([[0.3, 0.1], [0.1, 0.2]], dtype=DTYPE))
    particles = Particles(gp, policy, reward, num_particles=MANY_PARTICLES, include_noise=include_noise, seed=7)
    with torch.no_grad():
        exact, action = MomentMatching(gp, policy, reward, include_noise=include_noise).step(start)
        states, actions = particles.trajectories(start, 1)
    x1, u0 = states[:, 1], actions[:, 0]
    mc.assert_mean(exact.mean, x1, "next mean")
    centred = x1 - x1.mean(0)
    mc.assert_mean(exact.cov, centred[:, :, None] * centred[:, None, :], "next cov")
    mc.assert_mean(action.mean, u0, "action mean")


def test_one_step_close_to_moment_matching_with_angles(gp_factory):
    # Angles and a squashed RBF policy: moment matching approximates, particles sample exactly.
    gp, policy, reward = pendulum_parts(gp_factory)
    start = Gaussian(torch.tensor([0.2, 0.5, -0.1], dtype=DTYPE), 0.1 * torch.eye(3, dtype=DTYPE))
    with torch.no_grad():
        approx, _ = MomentMatching(gp, policy, reward, angle_dims=(1,)).step(start)
        states, _ = Particles(
            gp, policy, reward, angle_dims=(1,), num_particles=MANY_PARTICLES, include_noise=False
        ).trajectories(start, 1)
    x1 = states[:, 1]
    std = x1.std(0)
    assert ((approx.mean - x1.mean(0)).abs() <= APPROX_MEAN_TOL * std).all(), (approx.mean, x1.mean(0))
    ratio = approx.cov.diagonal().sqrt() / std
    assert ((ratio >= APPROX_STD_RATIO[0]) & (ratio <= APPROX_STD_RATIO[1])).all(), ratio


@pytest.mark.parametrize("include_noise", [False, True])
def test_particles_follow_the_gp_posterior_exactly(gp_factory, posterior, include_noise):
    # An independent per-particle reference (the conftest GP posterior, checked against GPyTorch)
    # with the propagator's own base noise gives the same paths to round-off.
    gp, policy, reward = pendulum_parts(gp_factory)
    particles = Particles(gp, policy, reward, angle_dims=(1,), num_particles=16, include_noise=include_noise, seed=3)
    start_std = torch.tensor([0.2, 0.45, 0.3], dtype=DTYPE)
    start = Gaussian(torch.tensor([0.1, 2.5, -0.3], dtype=DTYPE), torch.diag(start_std.square()))
    assert_marginal_paths(particles, gp, policy, start, 4, posterior, include_noise)


def test_rollout_structure(gp_factory):
    gp, policy, reward = pendulum_parts(gp_factory)
    particles = Particles(gp, policy, reward, angle_dims=(1,), num_particles=50)
    start = Gaussian(torch.zeros(3, dtype=DTYPE), 0.01 * torch.eye(3, dtype=DTYPE))
    rollout = particles.rollout(start, 4)
    assert rollout.states.mean.shape == (5, 3) and rollout.states.cov.shape == (5, 3, 3)
    assert rollout.actions.mean.shape == (4, 1) and rollout.actions.cov.shape == (4, 1, 1)
    assert rollout.rewards.shape == (4,) and rollout.value.shape == ()
    torch.testing.assert_close(rollout.value, rollout.rewards.sum())
    states, _ = particles.trajectories(start, 4)
    # Successor states x_1..x_H are scored (as PILCO), x_0 is not.
    torch.testing.assert_close(rollout.rewards[0], reward(states[:, 1]).mean())
    torch.testing.assert_close(rollout.states.mean[0], states[:, 0].mean(0))
    torch.testing.assert_close(rollout.states.cov[2], torch.cov(states[:, 2].T))
    torch.testing.assert_close(particles.expected_return(start, 4), rollout.value)


def test_common_random_numbers_and_seeds(gp_factory):
    gp, policy, reward = pendulum_parts(gp_factory)
    start = Gaussian(torch.zeros(3, dtype=DTYPE), 0.05 * torch.eye(3, dtype=DTYPE))

    def objective(**kwargs):
        return Particles(gp, policy, reward, angle_dims=(1,), num_particles=30, **kwargs)

    same = objective(seed=4)
    first = same.expected_return(start, 5)
    assert torch.equal(first, same.expected_return(start, 5))  # CRN: a deterministic objective
    assert torch.equal(first, objective(seed=4).expected_return(start, 5))
    assert not torch.equal(first, objective(seed=5).expected_return(start, 5))
    # The noise of a step does not depend on the horizon asked for.
    torch.testing.assert_close(same.base_noise(3)[1], same.base_noise(5)[1][:3], rtol=0, atol=0)


def test_gradients_reach_the_policy_and_are_finite(gp_factory):
    gp, policy, reward = pendulum_parts(gp_factory)
    particles = Particles(gp, policy, reward, angle_dims=(1,), num_particles=40, include_noise=False)
    policy.zero_grad()
    particles.expected_return(Gaussian(torch.zeros(3, dtype=DTYPE), 0.01 * torch.eye(3, dtype=DTYPE)), 10).backward()
    grads = [p.grad for p in policy.parameters()]
    assert all(g is not None and torch.isfinite(g).all() and g.abs().sum() > 0 for g in grads)
    policy.zero_grad()


def test_gradcheck_two_step_rollout_wrt_policy_and_start(gp_factory):
    gp = gp_factory(8, 2, 1, (1,), seed=41)
    policy = SquashedPolicy(RBFPolicy(3, 1, 3, generator=torch.Generator().manual_seed(2)), 1.0)
    particles = Particles(gp, policy, quadratic_reward(2, (1,)), angle_dims=(1,), num_particles=3, seed=1)
    start = Gaussian(torch.tensor([0.1, 0.4], dtype=DTYPE), 0.05 * torch.eye(2, dtype=DTYPE))
    # Fixed noise (draw 0): rollout() does not advance the draw.
    assert gradcheck_value_wrt_policy_and_start(policy, lambda s: particles.rollout(s, 2).value, start)


@pytest.mark.parametrize("every", [1, 2, 3])
def test_resample_every_k_calls(gp_factory, every):
    gp, policy, reward = linear_parts(gp_factory)
    particles = Particles(gp, policy, reward, num_particles=10, resample_every=every, seed=2)
    start = Gaussian(torch.zeros(2, dtype=DTYPE), 0.1 * torch.eye(2, dtype=DTYPE))
    calls = 3 * every
    values = [particles.expected_return(start, 3).detach() for _ in range(calls)]
    draws = [particles.draw_index(evaluation=i) for i in range(calls)]
    assert draws == [i // every for i in range(calls)]
    for i, j in itertools.combinations(range(calls), 2):
        assert torch.equal(values[i], values[j]) == (draws[i] == draws[j]), (i, j, every)
    # rollout() shows the noise of the latest evaluation and does not count as one.
    torch.testing.assert_close(particles.rollout(start, 3).value, values[-1], rtol=0, atol=0)
    assert particles.calls == calls


def test_never_resamples_by_default(gp_factory):
    gp, policy, reward = linear_parts(gp_factory)
    particles = Particles(gp, policy, reward, num_particles=10)
    start = Gaussian(torch.zeros(2, dtype=DTYPE), 0.1 * torch.eye(2, dtype=DTYPE))
    values = {float(particles.expected_return(start, 3).detach()) for _ in range(4)}
    assert len(values) == 1 and particles.draw_index() == 0


def test_non_finite_return_raises(gp_factory):
    gp, _, reward = linear_parts(gp_factory)
    policy = LinearPolicy(2, 1, bias=torch.tensor([float("nan")], dtype=DTYPE))
    particles = Particles(gp, policy, reward, num_particles=10)
    with pytest.raises(NonFiniteObjective, match=r"not finite.*step 1"):
        particles.expected_return(Gaussian(torch.zeros(2, dtype=DTYPE), 0.1 * torch.eye(2, dtype=DTYPE)), 3)


def test_safe_sqrt_clamps_with_a_finite_gradient():
    var = torch.tensor([-1e-12, 0.0, 1e-40, 4.0], dtype=DTYPE, requires_grad=True)
    root = _safe_sqrt(var.clamp_min(0.0))
    root.sum().backward()
    torch.testing.assert_close(root.detach(), torch.tensor([0.0, 0.0, 0.0, 2.0], dtype=DTYPE))
    torch.testing.assert_close(var.grad, torch.tensor([0.0, 0.0, 0.0, 0.25], dtype=DTYPE))


def test_singular_start_covariance(gp_factory):
    gp, policy, reward = linear_parts(gp_factory)
    particles = Particles(gp, policy, reward, num_particles=20)
    start = Gaussian(torch.tensor([0.1, 0.2], dtype=DTYPE), torch.diag(torch.tensor([0.1, 0.0], dtype=DTYPE)))
    states, _ = particles.trajectories(start, 2)
    torch.testing.assert_close(states[:, 0, 1], torch.full((20,), 0.2, dtype=DTYPE))


def test_batched_starts_equal_per_item(gp_factory, cov_factory):
    gp, policy, reward = pendulum_parts(gp_factory)
    particles = Particles(gp, policy, reward, angle_dims=(1,), num_particles=20)
    gen = torch.Generator().manual_seed(3)
    means = 0.3 * torch.randn(3, 3, generator=gen, dtype=DTYPE)
    covs = cov_factory(3, 0.3, gen, batch=(3,))
    batched = particles.rollout(Gaussian(means, covs), 4)
    assert batched.value.shape == (3,) and batched.states.mean.shape == (3, 5, 3)
    for i in range(3):
        single = particles.rollout(Gaussian(means[i], covs[i]), 4)
        torch.testing.assert_close(batched.value[i], single.value)
        torch.testing.assert_close(batched.states.cov[i], single.states.cov)


@pytest.mark.parametrize(("expected_reward", "gaussian_resampling"), [(False, False), (True, True)])
def test_batched_restarts_equal_separate_rollouts(gp_factory, expected_reward, gaussian_resampling):
    """A policy with ψ `R x ...`: one rollout (the same base noise) gives the R values and gradients of R rollouts."""
    gp, policy, reward = pendulum_parts(gp_factory)
    start = Gaussian(torch.tensor([0.1, 0.2, -0.1], dtype=DTYPE), 0.01 * torch.eye(3, dtype=DTYPE))
    assert_restarts_equal_separate(
        lambda p: Particles(gp, p, reward, angle_dims=(1,), num_particles=20, expected_reward=expected_reward,
                            gaussian_resampling=gaussian_resampling),
        policy, start, 5,
    )


def test_stacked_models_equal_per_model(gp_factory, cov_factory):
    gps = [gp_factory(30, 3, 1, (1,), seed=s) for s in (31, 32)]
    policy = SquashedPolicy(RBFPolicy(4, 1, 5, generator=torch.Generator().manual_seed(1)), 1.5)
    reward = quadratic_reward(3, (1,))
    stacked = Particles([g.posterior_cache() for g in gps], policy, reward, angle_dims=(1,), num_particles=20)
    gen = torch.Generator().manual_seed(4)
    means = 0.3 * torch.randn(2, 1, 3, generator=gen, dtype=DTYPE)  # 2 starts x 2 models
    covs = cov_factory(3, 0.3, gen, batch=(2, 1))
    batched = stacked.rollout(Gaussian(means, covs), 4)
    assert batched.value.shape == (2, 2)
    for i, j in itertools.product(range(2), range(2)):
        single = Particles(gps[j], policy, reward, angle_dims=(1,), num_particles=20)
        expected = single.rollout(Gaussian(means[i, 0], covs[i, 0]), 4)
        torch.testing.assert_close(batched.value[i, j], expected.value)
        torch.testing.assert_close(batched.states.cov[i, j], expected.states.cov)


def test_rejects_bad_settings_and_mismatched_parts(gp_factory):
    gp = gp_factory(10, 2, 1, (1,), seed=5)
    policy = LinearPolicy(3, 1)
    reward = quadratic_reward(2, (1,))
    with pytest.raises(ValueError, match="num_particles"):
        Particles(gp, policy, reward, angle_dims=(1,), num_particles=1)
    with pytest.raises(ValueError, match="resample_every"):
        Particles(gp, policy, reward, angle_dims=(1,), resample_every=-1)
    with pytest.raises(ValueError, match="GP input"):
        Particles(gp, policy, reward, angle_dims=())
    with pytest.raises(ValueError, match="reward"):
        Particles(gp, policy, quadratic_reward(3), angle_dims=(1,))
    particles = Particles(gp, policy, reward, angle_dims=(1,), num_particles=4)
    with pytest.raises(ValueError, match="2-D"):
        particles.rollout(Gaussian(torch.zeros(3, dtype=DTYPE), torch.eye(3, dtype=DTYPE)), 3)
    with pytest.raises(ValueError, match="horizon"):
        particles.rollout(Gaussian(torch.zeros(2, dtype=DTYPE), torch.eye(2, dtype=DTYPE)), 0)


def test_config_builds_particles_seeded_by_the_run(gp_factory):
    register_configs()
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        cfg = compose(config_name="train", overrides=["propagation=particles", "seed=11"])
    gp, policy, reward = pendulum_parts(gp_factory)
    built = instantiate(cfg.propagation)(gp, policy, reward, angle_dims=(1,))
    assert isinstance(built, Particles)
    assert (built.seed, built.num_particles, built.resample_every, built.include_noise) == (11, 400, 0, True)
    assert built.expected_reward  # the loop's default: the Rao-Blackwellised reward


def test_float32_propagation_agrees_with_float64(gp_factory):
    gp, policy, reward = pendulum_parts(gp_factory)
    start = Gaussian(torch.zeros(3, dtype=DTYPE), 0.05 * torch.eye(3, dtype=DTYPE))
    reference = Particles(gp, policy, reward, angle_dims=(1,), num_particles=30).rollout(start, 5)
    single = Particles(gp, policy.to(torch.float32), reward, angle_dims=(1,), num_particles=30, dtype=torch.float32)
    rollout = single.rollout(start, 5)
    assert rollout.value.dtype == torch.float32
    torch.testing.assert_close(rollout.value.double(), reference.value, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("include_noise", [False, True])
def test_expected_reward_is_the_same_expectation_with_less_variance(gp_factory, include_noise):
    # Without angles E[r(x_t) | x_{t−1}] is exact, so both estimators have the same mean over the
    # particles' paths: compare at many particles within 5 combined standard errors.
    gp, policy, reward = linear_parts(gp_factory)
    start = Gaussian(torch.tensor([0.1, -0.2], dtype=DTYPE), 0.05 * torch.eye(2, dtype=DTYPE))
    per_particle = {}
    for expected in (False, True):
        particles = Particles(gp, policy, reward, num_particles=20_000, include_noise=include_noise,
                              expected_reward=expected, seed=5)
        states, _, predictive = particles._paths(start, 3, None)
        per_particle[expected] = (reward.expected(predictive) if expected else reward(states[..., 1:, :])).sum(-1)
        value = particles.rollout(start, 3).value
        torch.testing.assert_close(value, per_particle[expected].mean())
    plain, smooth = per_particle[False], per_particle[True]
    std_err = (plain.var() / plain.numel() + smooth.var() / smooth.numel()).sqrt()
    assert (plain.mean() - smooth.mean()).abs() <= 5 * std_err
    assert smooth.var() < plain.var()  # per step it cannot add variance; here the sum has less too


def test_expected_reward_gradcheck(gp_factory):
    gp, policy, reward = pendulum_parts(gp_factory, num_basis=3)
    particles = Particles(gp, policy, reward, angle_dims=(1,), num_particles=6, include_noise=True,
                          expected_reward=True, seed=2)
    start = Gaussian(torch.tensor([0.1, 0.3, -0.2], dtype=DTYPE), 0.02 * torch.eye(3, dtype=DTYPE))
    assert gradcheck_value_wrt_policy_and_start(policy, lambda s: particles.rollout(s, 2).value, start)


def test_gaussian_resample_keeps_the_sample_mean_and_covariance():
    # Whitened noise (sample mean 0, sample covariance I): the redrawn cloud has exactly the
    # sample mean and covariance of the cloud it replaces, per batch item.
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(2, 50, 3, generator=gen, dtype=DTYPE) @ torch.tensor([[1.0, 0.3, 0], [0, 0.5, 0.2], [0, 0, 2]],
                                                                         dtype=DTYPE)
    noise = torch.randn(50, 3, generator=gen, dtype=DTYPE)
    noise = noise - noise.mean(0)
    noise = noise @ torch.linalg.inv(torch.linalg.cholesky(torch.cov(noise.T))).mT
    redrawn = _gaussian_resample(x, noise)
    torch.testing.assert_close(redrawn.mean(-2), x.mean(-2), rtol=0, atol=1e-12)
    for item in range(2):
        torch.testing.assert_close(torch.cov(redrawn[item].T), torch.cov(x[item].T), rtol=1e-10, atol=1e-12)


def test_gaussian_resampling_converges_to_moment_matching_over_steps(gp_factory, mc):
    # No angles, a linear policy: moment matching's step is exact from a Gaussian, and it
    # moment-matches after every step, as Gaussian resampling does. So over several steps the
    # resampled particles converge to the moment-matching trajectory; plain particles do not (the
    # state distribution stops being Gaussian). Tolerance: the last step's standard error, scaled
    # by √steps for the independent error each earlier refit carries forward.
    gp, policy, reward = linear_parts(gp_factory)
    start = Gaussian(torch.tensor([0.3, -0.4], dtype=DTYPE), torch.tensor([[0.3, 0.1], [0.1, 0.2]], dtype=DTYPE))
    steps = 6
    with torch.no_grad():
        exact = MomentMatching(gp, policy, reward).rollout(start, steps).states

    def worst_error(gaussian_resampling: bool) -> float:
        """The largest error of the last step's mean and covariance, in standard errors."""
        particles = Particles(gp, policy, reward, num_particles=MANY_PARTICLES, include_noise=False,
                              gaussian_resampling=gaussian_resampling, seed=9)
        with torch.no_grad():
            last = particles.trajectories(start, steps)[0][:, steps]
        centred = last - last.mean(0)
        products = centred[:, :, None] * centred[:, None, :]
        mean_err = (exact.mean[steps] - last.mean(0)).abs() / (last.std(0) / MANY_PARTICLES**0.5)
        cov_err = (exact.cov[steps] - products.mean(0)).abs() / (products.std(0) / MANY_PARTICLES**0.5)
        return max(float(mean_err.max()), float(cov_err.max()))

    limit = mc.z * steps**0.5
    assert worst_error(True) <= limit
    assert worst_error(False) > limit


def test_gaussian_resampling_seeds_and_gradcheck(gp_factory):
    gp = gp_factory(8, 2, 1, (1,), seed=41)
    policy = SquashedPolicy(RBFPolicy(3, 1, 3, generator=torch.Generator().manual_seed(2)), 1.0)
    reward = quadratic_reward(2, (1,))
    start = Gaussian(torch.tensor([0.1, 0.4], dtype=DTYPE), 0.05 * torch.eye(2, dtype=DTYPE))

    def objective(**kwargs):
        return Particles(gp, policy, reward, angle_dims=(1,), num_particles=6, seed=1, **kwargs)

    resampled = objective(gaussian_resampling=True)
    value = resampled.expected_return(start, 4)
    assert torch.equal(value, objective(gaussian_resampling=True).expected_return(start, 4))
    assert not torch.equal(value, objective().expected_return(start, 4))
    # The start and step noise are those of plain particles: resampling adds a stream.
    plain_noise, noise = objective().base_noise(4), resampled.base_noise(4)
    assert plain_noise.resampling is None and noise.resampling.shape == (4, 6, 2)
    assert torch.equal(plain_noise.start, noise.start) and torch.equal(plain_noise.steps, noise.steps)
    assert gradcheck_value_wrt_policy_and_start(policy, lambda s: resampled.rollout(s, 2).value, start)


@pytest.mark.parametrize("scale", [0.5, 4.0])
def test_reward_width_scale_scores_the_same_paths_with_the_widened_reward(gp_factory, scale):
    """reward_width_scale = k: the same particles, each search reward r(x)^(1/k²) (W / k²); k = 1: the task's."""
    gp, policy, reward = pendulum_parts(gp_factory)
    start = Gaussian(torch.tensor([0.1, 2.5, -0.2], dtype=DTYPE), 0.05 * torch.eye(3, dtype=DTYPE))

    def particles(**kwargs):
        return Particles(gp, policy, reward, angle_dims=(1,), num_particles=30, seed=6, **kwargs)

    plain, wide = particles(), particles(reward_width_scale=scale)
    assert plain.reward is reward and plain.search_reward is reward
    assert wide.reward is reward and torch.equal(wide.search_reward.reward.weight, reward.weight / scale**2)
    assert isinstance(wide.search_reward, SearchReward) and wide.search_reward.is_search_reward
    with torch.no_grad():
        states, _ = plain.trajectories(start, 5)
        assert torch.equal(wide.trajectories(start, 5)[0], states)  # the reward does not move the particles
        value, wide_value = plain.expected_return(start, 5), wide.expected_return(start, 5)
    torch.testing.assert_close(value, reward(states[:, 1:]).sum(-1).mean(), rtol=1e-12, atol=0)
    predicted = (reward(states[:, 1:]) ** (1 / scale**2)).sum(-1).mean()
    torch.testing.assert_close(wide_value, predicted, rtol=1e-12, atol=0)
    assert (wide_value > value) == (scale > 1)  # a wider reward pays more away from the target, everywhere
    # Predictions (rollout, figures) score the task's reward; only the search's objective is widened.
    with torch.no_grad():
        torch.testing.assert_close(wide.rollout(start, 5).value, value, rtol=1e-12, atol=0)


def test_reward_width_scale_reaches_the_expected_reward(gp_factory):
    gp, policy, reward = pendulum_parts(gp_factory)
    start = Gaussian(torch.tensor([0.1, 2.5, -0.2], dtype=DTYPE), 0.05 * torch.eye(3, dtype=DTYPE))
    wide = Particles(gp, policy, reward, angle_dims=(1,), num_particles=20, expected_reward=True,
                     reward_width_scale=2.0, seed=6)
    with torch.no_grad():
        _, _, predictive = wide._paths(start, 4, None)
        want = reward.widened(2.0).expected(predictive).sum(-1).mean()
        torch.testing.assert_close(wide.expected_return(start, 4), want, rtol=1e-12, atol=0)


@pytest.mark.parametrize("weight", [0.25, 0.5])
def test_reward_task_weight_mixes_the_widened_and_the_task_reward_on_the_same_paths(gp_factory, weight):
    """reward_task_weight = w: the search scores (1 − w) r^(1/k²) + w r on the same particles; w = 1 is the task's."""
    gp, policy, reward = pendulum_parts(gp_factory)
    start = Gaussian(torch.tensor([0.1, 2.5, -0.2], dtype=DTYPE), 0.05 * torch.eye(3, dtype=DTYPE))

    def particles(**kwargs):
        return Particles(gp, policy, reward, angle_dims=(1,), num_particles=30, seed=6, reward_width_scale=3.0,
                         **kwargs)

    mixed, task_only = particles(reward_task_weight=weight), particles(reward_task_weight=1.0)
    assert task_only.search_reward is reward and mixed.reward is reward
    with torch.no_grad():
        states, _ = mixed.trajectories(start, 5)
        r = reward(states[:, 1:])
        want = ((1 - weight) * r ** (1 / 9) + weight * r).sum(-1).mean()
        torch.testing.assert_close(mixed.expected_return(start, 5), want, rtol=1e-12, atol=0)
        torch.testing.assert_close(mixed.rollout(start, 5).value, r.sum(-1).mean(), rtol=1e-12, atol=0)


def test_search_cost_task_scores_the_tasks_cost_mixed_with_its_reward(gp_factory):
    """search_cost=task: (1 − w) c(x) + w r(x) on the same particles, c the task's angle-distance cost."""
    gp, policy, reward = pendulum_parts(gp_factory)
    start = Gaussian(torch.tensor([0.1, 2.5, -0.2], dtype=DTYPE), 0.05 * torch.eye(3, dtype=DTYPE))
    cost = AngleDistanceReward(3, (1,), [0.0, math.pi, 0.0], [1.0, 2.0, math.inf])
    prop = Particles(gp, policy, reward, angle_dims=(1,), num_particles=30, seed=6, search_cost="task",
                     task_search_cost=cost, reward_task_weight=0.25)
    widened = Particles(gp, policy, reward, angle_dims=(1,), num_particles=30, seed=6, search_cost="widened",
                        task_search_cost=cost, reward_width_scale=2.0)
    with torch.no_grad():
        states, _ = prop.trajectories(start, 5)
        after = states[:, 1:]
        want = (0.75 * cost(after) + 0.25 * reward(after)).sum(-1).mean()
        torch.testing.assert_close(prop.expected_return(start, 5), want, rtol=1e-12, atol=0)
        torch.testing.assert_close(prop.rollout(start, 5).value, reward(after).sum(-1).mean(), rtol=1e-12, atol=0)
    assert torch.equal(widened.search_reward.reward.weight, reward.weight / 4)  # widened ignores the task's cost
    with pytest.raises(UserError, match="declares no search_reward"):
        Particles(gp, policy, reward, angle_dims=(1,), search_cost="task")
    with pytest.raises(UserError, match=r"propagation\.search_cost must be one of"):
        Particles.check_settings(search_cost="tip")


@pytest.mark.parametrize("weight", [-0.1, 1.5, float("nan")])
def test_a_bad_reward_task_weight_is_a_user_error(gp_factory, weight):
    with pytest.raises(UserError, match=r"propagation\.reward_task_weight must be in \[0, 1\]"):
        Particles.check_settings(reward_task_weight=weight)


@pytest.mark.parametrize("scale", [0.0, -2.0, float("nan")])
def test_a_bad_reward_width_scale_is_a_user_error(gp_factory, scale):
    with pytest.raises(UserError, match=r"propagation\.reward_width_scale must be > 0"):
        Particles.check_settings(reward_width_scale=scale)
    gp, policy, reward = linear_parts(gp_factory)
    with pytest.raises(UserError, match="reward_width_scale"):
        Particles(gp, policy, reward, reward_width_scale=scale)


def test_search_start_scale_narrows_the_searchs_start_only(gp_factory):
    # The search's objective starts from N(μ_0, s² Σ_0); predictions (rollout) keep the task's start.
    gp, policy, reward = pendulum_parts(gp_factory)
    start = Gaussian(torch.tensor([0.1, 0.3, -0.2], dtype=DTYPE), 0.2 * torch.eye(3, dtype=DTYPE))
    narrow = Particles(gp, policy, reward, angle_dims=(1,), num_particles=30, search_start_scale=0.3, seed=4)
    plain = Particles(gp, policy, reward, angle_dims=(1,), num_particles=30, seed=4)
    expected = plain.rollout(Gaussian(start.mean, 0.09 * start.cov), 4).value
    torch.testing.assert_close(narrow.expected_return(start, 4), expected, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(narrow.rollout(start, 4).value, plain.rollout(start, 4).value, rtol=0, atol=0)
    assert not torch.equal(narrow.rollout(start, 4).value, expected)
    for bad in (0.0, 1.5):
        with pytest.raises(UserError, match=r"propagation\.search_start_scale must be in \(0, 1\]"):
            Particles(gp, policy, reward, angle_dims=(1,), search_start_scale=bad)
