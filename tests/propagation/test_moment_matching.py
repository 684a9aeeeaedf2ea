"""MomentMatching: one step against Monte Carlo, rollouts against sampling, batching, gradients."""

from __future__ import annotations

import itertools

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from qtl.features import AngleFeatures
from qtl.gaussian import Gaussian
from qtl.kernels import Engine
from qtl.policies import LinearPolicy, RBFPolicy, SquashedPolicy
from qtl.propagation import MomentMatching
from tests.helpers import gradcheck_value_wrt_policy_and_start, quadratic_reward
from tests.propagation.restarts import assert_restarts_equal_separate

DTYPE = torch.float64
NUM_SAMPLES = 100_000
# Loose agreement of a moment-matched step or rollout with sampling, where moment matching is
# only an approximation (see the tests): mean error in units of the sampled standard deviation,
# and the ratio of predicted to sampled standard deviation per dimension.
APPROX_MEAN_TOL = 0.15
APPROX_STD_RATIO = (0.75, 1.25)
APPROX_VALUE_REL_TOL = 0.1


@pytest.fixture(scope="module")
def linear_system(gp_factory):
    """No angles, a linear policy: every stage of a step is exact (the GP input is Gaussian)."""
    gp = gp_factory(40, 2, 1, seed=21)
    policy = LinearPolicy(2, 1, weight=torch.tensor([[0.8, -0.5]], dtype=DTYPE), bias=torch.tensor([0.2], dtype=DTYPE))
    return gp, MomentMatching(gp.posterior_cache(), policy, quadratic_reward(2))


@pytest.fixture(scope="module")
def pendulum_system(gp_factory):
    """A 3-D state with an angle, a squashed RBF policy: PILCO's full configuration."""
    gp = gp_factory(40, 3, 1, (1,), seed=22)
    gen = torch.Generator().manual_seed(23)
    policy = SquashedPolicy(
        RBFPolicy(4, 1, 8, targets=torch.randn(8, 1, generator=gen, dtype=DTYPE), generator=gen), 2.0
    )
    return gp, MomentMatching(gp.posterior_cache(), policy, quadratic_reward(3, (1,)), angle_dims=(1,))


def simulate(gp, propagator, x: torch.Tensor, steps: int, gen: torch.Generator, posterior):
    """Particles through the same policy and GP, a fresh GP draw per particle and step."""
    features = AngleFeatures(propagator.state_dim, propagator.features.angle_dims)
    cache = gp.posterior_cache()
    rewards = []
    with torch.no_grad():
        for _ in range(steps):
            y = features(x)
            mean, var = posterior(cache, torch.cat([y, propagator.policy(y)], dim=-1))
            x = x + mean + var.clamp_min(0).sqrt() * torch.randn(x.shape, generator=gen, dtype=DTYPE)
            rewards.append(propagator.reward(x))
    return x, torch.stack(rewards, dim=-1)


def test_exact_step_against_monte_carlo(linear_system, mc, posterior):
    # With no angles and a linear policy, [x, u] is jointly Gaussian, so the step is exact.
    gp, propagator = linear_system
    gen = torch.Generator().manual_seed(0)
    start = Gaussian(torch.tensor([0.3, -0.4], dtype=DTYPE), torch.tensor([[0.3, 0.1], [0.1, 0.2]], dtype=DTYPE))
    with torch.no_grad():
        nxt, action = propagator.step(start)
        x = start.sample(NUM_SAMPLES, generator=gen)
        u = propagator.policy(x)
        mean, var = posterior(gp.posterior_cache(), torch.cat([x, u], dim=-1))
    mc.assert_mean(action.mean, u, "action mean")
    mc.assert_mean(nxt.mean, x + mean, "next mean")
    # cov x' = cov(x + E[Δ | x]) + E[var(Δ | x)] (law of total variance).
    centred = x + mean - (x + mean).mean(0)
    terms = centred[:, :, None] * centred[:, None, :] + torch.diag_embed(var)
    mc.assert_mean(nxt.cov, terms, "next cov")


def test_full_step_against_monte_carlo_loosely(pendulum_system, posterior):
    # Angles and a squashed RBF policy: the policy sees the moment-matched Gaussian of the
    # features, and cov[x, u], cov[x, Δ] are chained as if the joints were Gaussian (PILCO), so
    # one step is close to, not equal to, the sampled distribution.
    gp, propagator = pendulum_system
    gen = torch.Generator().manual_seed(1)
    start = Gaussian(torch.tensor([0.2, 0.5, -0.1], dtype=DTYPE), 0.1 * torch.eye(3, dtype=DTYPE))
    with torch.no_grad():
        nxt, _ = propagator.step(start)
    x, _ = simulate(gp, propagator, start.sample(NUM_SAMPLES, generator=gen), 1, gen, posterior)
    assert_close_loosely(nxt, x)


def assert_close_loosely(predicted: Gaussian, x: torch.Tensor) -> None:
    std = x.std(0)
    assert ((predicted.mean - x.mean(0)).abs() <= APPROX_MEAN_TOL * std).all(), (predicted.mean, x.mean(0))
    ratio = predicted.cov.diagonal().sqrt() / std
    assert ((ratio >= APPROX_STD_RATIO[0]) & (ratio <= APPROX_STD_RATIO[1])).all(), ratio


@pytest.mark.parametrize("system", ["linear_system", "pendulum_system"])
def test_rollout_against_sampling_loosely(system, request, posterior):
    # After several steps the true state distribution is no longer Gaussian (the GP and policy
    # are nonlinear, and each step re-fits a Gaussian), so only the first two moments are
    # compared, loosely. The particles draw the GP afresh at every step, as moment matching
    # assumes (no correlation of the function across steps).
    gp, propagator = request.getfixturevalue(system)
    gen = torch.Generator().manual_seed(2)
    dim = propagator.state_dim
    start = Gaussian(torch.full((dim,), 0.2, dtype=DTYPE), 0.05 * torch.eye(dim, dtype=DTYPE))
    horizon = 5
    with torch.no_grad():
        rollout = propagator.rollout(start, horizon)
    x, rewards = simulate(gp, propagator, start.sample(NUM_SAMPLES, generator=gen), horizon, gen, posterior)
    assert_close_loosely(Gaussian(rollout.states.mean[-1], rollout.states.cov[-1]), x)
    sampled_value = rewards.sum(-1).mean()
    assert abs(rollout.value - sampled_value) <= APPROX_VALUE_REL_TOL * sampled_value


def test_rollout_structure(pendulum_system):
    _, propagator = pendulum_system
    start = Gaussian(torch.zeros(3, dtype=DTYPE), 0.01 * torch.eye(3, dtype=DTYPE))
    rollout = propagator.rollout(start, 4)
    assert rollout.states.mean.shape == (5, 3) and rollout.states.cov.shape == (5, 3, 3)
    assert rollout.actions.mean.shape == (4, 1) and rollout.rewards.shape == (4,)
    torch.testing.assert_close(rollout.value, rollout.rewards.sum())
    # PILCO scores the successor states x_1..x_H, not x_0.
    first, _ = propagator.step(start)
    torch.testing.assert_close(rollout.rewards[0], propagator.reward.expected(first))
    torch.testing.assert_close(propagator.expected_return(start, 4), rollout.value)


def test_output_noise_option(gp_factory):
    gp = gp_factory(20, 2, 1, seed=24)
    policy = LinearPolicy(2, 1, generator=torch.Generator().manual_seed(0))
    start = Gaussian(torch.zeros(2, dtype=DTYPE), 0.1 * torch.eye(2, dtype=DTYPE))
    latent, _ = MomentMatching(gp, policy, quadratic_reward(2)).step(start)
    noisy, _ = MomentMatching(gp, policy, quadratic_reward(2), include_noise=True).step(start)
    torch.testing.assert_close(noisy.cov - latent.cov, torch.diag(gp.hyperparameters.noise_variance))


def test_batched_starts_equal_per_item(pendulum_system, cov_factory):
    _, propagator = pendulum_system
    gen = torch.Generator().manual_seed(3)
    means = 0.3 * torch.randn(3, 3, generator=gen, dtype=DTYPE)
    covs = cov_factory(3, 0.3, gen, batch=(3,))
    batched = propagator.rollout(Gaussian(means, covs), 6)
    for i in range(3):
        single = propagator.rollout(Gaussian(means[i], covs[i]), 6)
        torch.testing.assert_close(batched.value[i], single.value)
        torch.testing.assert_close(batched.states.mean[i], single.states.mean)
        torch.testing.assert_close(batched.states.cov[i], single.states.cov)


@pytest.mark.parametrize(("inner", "kernels"), [("rbf", "torch"), ("linear", "torch"), ("rbf", "native")])
def test_batched_restarts_equal_separate_rollouts(gp_factory, inner, kernels):
    """A policy with ψ `R x ...`: one rollout gives the R values and gradients of R rollouts (1e-10 relative)."""
    gp = gp_factory(40, 3, 1, (1,), seed=22)
    gen = torch.Generator().manual_seed(23)
    core = (RBFPolicy(4, 1, 8, targets=torch.randn(8, 1, generator=gen, dtype=DTYPE), generator=gen)
            if inner == "rbf" else LinearPolicy(4, 1, generator=gen))
    start = Gaussian(torch.tensor([0.1, 0.2, -0.1], dtype=DTYPE), 0.01 * torch.eye(3, dtype=DTYPE))
    engine = Engine.resolve("auto" if kernels == "native" else kernels, "reference")
    if engine.exp_sums != kernels:
        pytest.skip("the native exp-sum kernel is not built")
    assert_restarts_equal_separate(
        lambda policy: MomentMatching(gp, policy, quadratic_reward(3, (1,)), angle_dims=(1,), engine=engine),
        SquashedPolicy(core, 2.0), start, 6,
    )


def test_stacked_models_equal_per_model(gp_factory, cov_factory):
    gps = [gp_factory(30, 3, 1, (1,), seed=s) for s in (31, 32)]
    policy = SquashedPolicy(RBFPolicy(4, 1, 5, generator=torch.Generator().manual_seed(1)), 1.5)
    reward = quadratic_reward(3, (1,))
    stacked = MomentMatching([g.posterior_cache() for g in gps], policy, reward, angle_dims=(1,))
    gen = torch.Generator().manual_seed(4)
    means = 0.3 * torch.randn(2, 1, 3, generator=gen, dtype=DTYPE)  # 2 starts x 2 models
    covs = cov_factory(3, 0.3, gen, batch=(2, 1))
    batched = stacked.rollout(Gaussian(means, covs), 5)
    assert batched.value.shape == (2, 2)
    for i, j in itertools.product(range(2), range(2)):
        single = MomentMatching(gps[j], policy, reward, angle_dims=(1,)).rollout(Gaussian(means[i, 0], covs[i, 0]), 5)
        torch.testing.assert_close(batched.value[i, j], single.value)
        torch.testing.assert_close(batched.states.cov[i, j], single.states.cov)


def test_gradcheck_three_step_rollout_wrt_policy(gp_factory):
    gp = gp_factory(10, 2, 1, (1,), seed=41)
    policy = SquashedPolicy(RBFPolicy(3, 1, 3, generator=torch.Generator().manual_seed(2)), 1.0)
    propagator = MomentMatching(gp, policy, quadratic_reward(2, (1,)), angle_dims=(1,))
    start = Gaussian(torch.tensor([0.1, 0.4], dtype=DTYPE), 0.05 * torch.eye(2, dtype=DTYPE))
    assert gradcheck_value_wrt_policy_and_start(policy, lambda s: propagator.expected_return(s, 3), start)


def test_gradient_reaches_policy_parameters(pendulum_system):
    _, propagator = pendulum_system
    propagator.policy.zero_grad()
    start = Gaussian(torch.zeros(3, dtype=DTYPE), 0.01 * torch.eye(3, dtype=DTYPE))
    propagator.expected_return(start, 10).backward()
    grads = [p.grad for p in propagator.policy.parameters()]
    assert all(g is not None and torch.isfinite(g).all() and g.abs().sum() > 0 for g in grads)
    propagator.policy.zero_grad()


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(1e-3, 1.0))
def test_state_covariances_stay_psd(pendulum_system, psd, cov_factory, seed, scale):
    _, propagator = pendulum_system
    gen = torch.Generator().manual_seed(seed)
    start = Gaussian(torch.randn(3, generator=gen, dtype=DTYPE), cov_factory(3, scale, gen))
    with torch.no_grad():
        rollout = propagator.rollout(start, 8)
    psd(rollout.states.cov, rel_tol=1e-8)
    psd(rollout.actions.cov, rel_tol=1e-8)
    assert ((rollout.rewards >= 0) & (rollout.rewards <= 1)).all()


def test_rejects_mismatched_parts(gp_factory):
    gp = gp_factory(10, 2, 1, (1,), seed=5)
    policy = LinearPolicy(3, 1)
    with pytest.raises(ValueError, match="GP input"):
        MomentMatching(gp, policy, quadratic_reward(2), angle_dims=())
    with pytest.raises(ValueError, match="reward"):
        MomentMatching(gp, policy, quadratic_reward(3), angle_dims=(1,))
    propagator = MomentMatching(gp, policy, quadratic_reward(2, (1,)), angle_dims=(1,))
    with pytest.raises(ValueError):
        propagator.rollout(Gaussian(torch.zeros(3, dtype=DTYPE), torch.eye(3, dtype=DTYPE)), 3)
    with pytest.raises(ValueError):
        propagator.rollout(Gaussian(torch.zeros(2, dtype=DTYPE), torch.eye(2, dtype=DTYPE)), 0)


# float32 moment matching on the test problems (noisy data: a well-conditioned K + σ_ε²I) against
# float64: the value within this relative tolerance, and state moments and gradients within this
# fraction of their largest magnitude (observed: 8e-7; 3e-6, 8e-5 and 3e-5). On near-noiseless data
# (σ_ε² at the SNR bound, e.g. the cart-pole benchmark's) float32 is not safe: see docs/benchmarks.md.
FLOAT32_VALUE_REL_TOL = 1e-5
FLOAT32_SCALED_TOL = 1e-3


def assert_close_to_scale(actual: torch.Tensor, expected: torch.Tensor, tol: float) -> None:
    """max |actual − expected| <= tol · max |expected|."""
    assert float((actual.double() - expected).abs().max()) <= tol * float(expected.abs().max())


def test_float32_rollout_agrees_with_float64(gp_factory):
    gp = gp_factory(40, 3, 1, (1,), seed=22)
    gen = torch.Generator().manual_seed(23)
    policy = SquashedPolicy(
        RBFPolicy(4, 1, 8, targets=torch.randn(8, 1, generator=gen, dtype=DTYPE), generator=gen), 2.0
    )
    start = Gaussian(torch.tensor([0.1, 0.2, -0.3], dtype=DTYPE), 0.02 * torch.eye(3, dtype=DTYPE))
    results = {}
    for dtype in (torch.float64, torch.float32):
        policy = policy.to(dtype)
        policy.zero_grad()
        rollout = MomentMatching(gp, policy, quadratic_reward(3, (1,)), angle_dims=(1,), dtype=dtype).rollout(start, 8)
        rollout.value.backward()
        grads = torch.cat([p.grad.flatten() for p in policy.parameters()])
        assert rollout.value.dtype == dtype and grads.dtype == dtype
        results[dtype] = (rollout, grads)
    (double, double_grad), (single, single_grad) = results[torch.float64], results[torch.float32]
    torch.testing.assert_close(single.value.double(), double.value, rtol=FLOAT32_VALUE_REL_TOL, atol=0.0)
    assert_close_to_scale(single.states.mean, double.states.mean, FLOAT32_SCALED_TOL)
    assert_close_to_scale(single.states.cov, double.states.cov, FLOAT32_SCALED_TOL)
    assert_close_to_scale(single_grad, double_grad, FLOAT32_SCALED_TOL)
