"""Saturating reward (Eq. 13) in torch: per-state values, expectation under a Gaussian, gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from qtl.envs.rewards import SaturatingReward
from qtl.gaussian import Gaussian
from qtl.rewards import AngleDistanceReward, ExpectedSaturatingReward, RewardMixture

DTYPE = torch.float64
NUM_SAMPLES = 100_000
POLE_LENGTH = 0.6
COST_WIDTH = 0.25
# Loose check of the angle case: E[r] uses the moment-matched Gaussian of (…, sin θ, cos θ),
# which is not the distribution of the features; with small angle spread the error is small.
ANGLE_REWARD_REL_TOL = 0.05


def cartpole_spec(length: float = POLE_LENGTH, width: float = COST_WIDTH) -> SaturatingReward:
    """Tip distance of ../shared/TASKS.md: y = [x, ẋ, θ̇, sin θ, cos θ], y* = (0, 0, 0, 0, −1)."""
    tip = np.array([[1.0, 0.0, 0.0, length, 0.0], [0.0, 0.0, 0.0, 0.0, -length]])
    weight = tip.T @ tip
    return SaturatingReward(
        state_dim=4,
        angle_dims=(2,),
        target=(0.0, 0.0, 0.0, 0.0, -1.0),
        weight=tuple(map(tuple, weight)),
        width=width,
    )


def plain_spec() -> SaturatingReward:
    """A 3-D state without angles and a full-rank weight."""
    weight = ((2.0, 0.3, 0.0), (0.3, 1.0, 0.1), (0.0, 0.1, 0.5))
    return SaturatingReward(state_dim=3, angle_dims=(), target=(0.5, -0.2, 1.0), weight=weight, width=0.8)


def test_per_state_value_matches_env_spec_and_tip_distance():
    spec = cartpole_spec()
    reward = ExpectedSaturatingReward.from_spec(spec)
    x = torch.randn(50, 4, generator=torch.Generator().manual_seed(0), dtype=DTYPE) * 2
    np.testing.assert_allclose(reward(x).numpy(), spec(x.numpy()), rtol=1e-12)
    pos, theta, ell = x[:, 0], x[:, 2], POLE_LENGTH
    d2 = pos**2 + 2 * pos * ell * theta.sin() + 2 * ell**2 + 2 * ell**2 * theta.cos()
    torch.testing.assert_close(reward(x), torch.exp(-d2 / (2 * COST_WIDTH**2)))
    upright = torch.tensor([0.0, 0.0, math.pi, 0.0], dtype=DTYPE)
    torch.testing.assert_close(reward(upright), torch.tensor(1.0, dtype=DTYPE))


def test_expectation_without_angles_against_monte_carlo(mc, cov_factory):
    reward = ExpectedSaturatingReward.from_spec(plain_spec())
    gen = torch.Generator().manual_seed(1)
    for scale in (0.1, 0.7, 2.0):
        state = Gaussian(torch.tensor([0.2, 0.1, 0.6], dtype=DTYPE), cov_factory(3, scale, gen))
        mc.assert_mean(reward.expected(state), reward(state.sample(NUM_SAMPLES, generator=gen)))


def test_augmented_expectation_against_monte_carlo(mc, cov_factory):
    # Exact check of the formula on Gaussian features (including a rank-deficient W).
    reward = ExpectedSaturatingReward.from_spec(cartpole_spec())
    gen = torch.Generator().manual_seed(2)
    y = Gaussian(torch.tensor([0.1, 0.0, 0.3, 0.2, -0.8], dtype=DTYPE), cov_factory(5, 0.3, gen))
    samples = y.sample(NUM_SAMPLES, generator=gen)
    err = samples - reward.target
    per_sample = torch.exp(-0.5 * torch.einsum("ni,ij,nj->n", err, reward.weight, err))
    mc.assert_mean(reward.expected_augmented(y), per_sample)


def test_expectation_with_angles_is_close_for_small_spread(cov_factory):
    reward = ExpectedSaturatingReward.from_spec(cartpole_spec())
    gen = torch.Generator().manual_seed(3)
    state = Gaussian(torch.tensor([0.05, 0.0, 3.0, 0.0], dtype=DTYPE), cov_factory(4, 0.1, gen))
    sampled = reward(state.sample(NUM_SAMPLES, generator=gen)).mean()
    assert abs(reward.expected(state) - sampled) <= ANGLE_REWARD_REL_TOL * sampled


def test_batched_and_delta_input():
    reward = ExpectedSaturatingReward.from_spec(cartpole_spec())
    means = torch.randn(3, 4, generator=torch.Generator().manual_seed(4), dtype=DTYPE)
    expected = reward.expected(Gaussian(means, torch.zeros(3, 4, 4, dtype=DTYPE)))
    torch.testing.assert_close(expected, reward(means))
    cov = 0.01 * torch.eye(4, dtype=DTYPE)
    batched = reward.expected(Gaussian(means, cov))
    for i in range(3):
        torch.testing.assert_close(batched[i], reward.expected(Gaussian(means[i], cov)))


@pytest.mark.parametrize("spec", [cartpole_spec(), plain_spec()], ids=["cartpole", "plain"])
def test_gradcheck(spec):
    reward = ExpectedSaturatingReward.from_spec(spec)
    gen = torch.Generator().manual_seed(5)
    dim = spec.state_dim
    mean = torch.randn(dim, generator=gen, dtype=DTYPE).requires_grad_()
    root = (0.3 * torch.randn(dim, dim, generator=gen, dtype=DTYPE)).requires_grad_()
    assert torch.autograd.gradcheck(lambda m, r: reward.expected(Gaussian(m, r @ r.T)), (mean, root))
    assert torch.autograd.gradcheck(reward, (mean,))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(1e-3, 10.0))
def test_expectation_is_a_probability(cov_factory, seed, scale):
    reward = ExpectedSaturatingReward.from_spec(cartpole_spec())
    gen = torch.Generator().manual_seed(seed)
    state = Gaussian(2 * torch.randn(4, generator=gen, dtype=DTYPE), cov_factory(4, scale, gen))
    value = reward.expected(state)
    assert 0.0 <= value <= 1.0


def test_rejects_bad_specs():
    with pytest.raises(ValueError):
        ExpectedSaturatingReward(2, (), [0.0, 0.0], [[1.0, 2.0], [0.0, 1.0]])
    with pytest.raises(ValueError):
        ExpectedSaturatingReward(2, (), [0.0, 0.0], [[-1.0, 0.0], [0.0, 1.0]])
    with pytest.raises(ValueError):
        ExpectedSaturatingReward(2, (1,), [0.0, 0.0], [[1.0, 0.0], [0.0, 1.0]])


@pytest.mark.parametrize("scale", [0.5, 2.0, 4.0])
def test_widened_reward_is_the_reward_of_a_wider_spec(scale, cov_factory):
    """widened(k): W / k², i.e. r(x)^(1/k²), and the same reward as the env spec with its width × k."""
    reward = ExpectedSaturatingReward.from_spec(cartpole_spec())
    wide = reward.widened(scale)
    x = 2 * torch.randn(50, 4, generator=torch.Generator().manual_seed(6), dtype=DTYPE)
    torch.testing.assert_close(wide(x), reward(x) ** (1 / scale**2), rtol=1e-12, atol=1e-300)
    spec = ExpectedSaturatingReward.from_spec(cartpole_spec(width=COST_WIDTH * scale))
    torch.testing.assert_close(wide(x), spec(x), rtol=1e-12, atol=0)
    state = Gaussian(torch.tensor([0.1, 0.0, 2.8, 0.3], dtype=DTYPE), cov_factory(4, 0.3, torch.Generator()))
    torch.testing.assert_close(wide.expected(state), spec.expected(state), rtol=1e-12, atol=0)
    assert (wide.state_dim, wide.features.angle_dims) == (4, (2,)) and torch.equal(wide.target, reward.target)
    far = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=DTYPE)  # hanging down, 1 m off: wider means more reward here
    assert (wide(far) > reward(far)) == (scale > 1)


def test_widening_leaves_the_reward_and_refuses_a_bad_scale():
    reward = ExpectedSaturatingReward.from_spec(plain_spec())
    weight = reward.weight.clone()
    torch.testing.assert_close(reward.widened(3.0).weight, weight / 9)
    torch.testing.assert_close(reward.widened(1.0).weight, weight, rtol=0, atol=0)
    assert torch.equal(reward.weight, weight)
    for scale in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match="width scale must be > 0"):
            reward.widened(scale)


def test_mixture_is_the_weighted_sum_and_its_expectation_against_monte_carlo(mc, cov_factory):
    """r = 0.3 r_wide + 0.7 r: per state exactly, and E[r] on a Gaussian without angles against Monte Carlo."""
    reward = ExpectedSaturatingReward.from_spec(plain_spec())
    wide = reward.widened(3.0)
    mix = RewardMixture([wide, reward], [0.3, 0.7])
    gen = torch.Generator().manual_seed(7)
    x = torch.randn(40, 3, generator=gen, dtype=DTYPE)
    torch.testing.assert_close(mix(x), 0.3 * wide(x) + 0.7 * reward(x), rtol=1e-14, atol=0)
    assert mix.state_dim == 3
    state = Gaussian(torch.tensor([0.2, 0.1, 0.6], dtype=DTYPE), cov_factory(3, 0.7, gen))
    mc.assert_mean(mix.expected(state), mix(state.sample(NUM_SAMPLES, generator=gen)))


def test_mixture_expectation_with_angles_and_gradcheck(cov_factory):
    reward = ExpectedSaturatingReward.from_spec(cartpole_spec())
    mix = RewardMixture([reward.widened(4.0), reward], [0.5, 0.5])
    state = Gaussian(torch.tensor([0.1, 0.0, 2.8, 0.3], dtype=DTYPE), cov_factory(4, 0.3, torch.Generator()))
    want = 0.5 * reward.widened(4.0).expected(state) + 0.5 * reward.expected(state)
    torch.testing.assert_close(mix.expected(state), want, rtol=1e-14, atol=0)
    x = torch.randn(6, 4, generator=torch.Generator().manual_seed(8), dtype=DTYPE, requires_grad=True)
    assert torch.autograd.gradcheck(mix, (x,))
    upright = torch.tensor([0.0, 0.0, math.pi, 0.0], dtype=DTYPE)
    torch.testing.assert_close(mix(upright), torch.tensor(1.0, dtype=DTYPE))  # the weights sum to 1: r ≤ 1 holds


def test_mixture_refuses_bad_parts_and_weights():
    reward = ExpectedSaturatingReward.from_spec(plain_spec())
    with pytest.raises(ValueError, match="as many weights as parts"):
        RewardMixture([reward], [0.5, 0.5])
    with pytest.raises(ValueError, match="as many weights as parts"):
        RewardMixture([], [])
    for weights in ([-0.1, 1.1], [0.0, 0.0], [math.nan, 1.0]):
        with pytest.raises(ValueError, match="weights must be >= 0"):
            RewardMixture([reward, reward], weights)
    with pytest.raises(ValueError, match="share the state dimension"):
        RewardMixture([reward, ExpectedSaturatingReward.from_spec(cartpole_spec())], [0.5, 0.5])


def mcpilco_cost() -> AngleDistanceReward:
    """MC-PILCO's cart-pole cost in ½-form: x* = 0 (σ = 1/√2 m), θ* = π (σ = 3/√2 rad), speeds left out."""
    widths = [1 / math.sqrt(2), math.inf, 3 / math.sqrt(2), math.inf]
    return AngleDistanceReward(4, (2,), [0.0, 0.0, math.pi, 0.0], widths)


def test_angle_distance_reward_is_mcpilco_cart_pole_cost():
    """exp(−((|θ| − π)/3)² − x²) for θ in [−π, π), whatever the number of turns; speeds do not count."""
    cost = mcpilco_cost()
    gen = torch.Generator().manual_seed(9)
    x = torch.rand(200, 4, generator=gen, dtype=DTYPE) * torch.tensor([4.0, 20.0, 2 * math.pi, 20.0]) - torch.tensor(
        [2.0, 10.0, math.pi, 10.0])
    want = torch.exp(-((x[:, 2].abs() - math.pi) / 3) ** 2 - x[:, 0] ** 2)
    torch.testing.assert_close(cost(x), want, rtol=1e-12, atol=0)
    turned = x + torch.tensor([0.0, 0.0, 2 * math.pi, 0.0], dtype=DTYPE) * torch.randint(-3, 4, (200, 1), generator=gen)
    torch.testing.assert_close(cost(turned), want, rtol=1e-9, atol=1e-12)
    assert cost.state_dim == 4
    hanging = torch.tensor([[0.0, 0.0, s, 0.0] for s in (0.0, 0.1, 0.2)], dtype=DTYPE)
    r = cost(hanging)
    assert r[1] - r[0] > 0.4 * (r[2] - r[0]) > 0  # first order in the swing from hanging (a quadratic gives 0.25)


def test_absolute_angles_score_each_extra_turn_as_mcpilco_writes_it():
    """absolute_angles: exp(−((|θ| − π)/3)² − x²) on the raw angle; within one turn the wrapped form's value."""
    widths = [1 / math.sqrt(2), math.inf, 3 / math.sqrt(2), math.inf]
    cost = AngleDistanceReward(4, (2,), [0.0, 0.0, math.pi, 0.0], widths, absolute_angles=True)
    gen = torch.Generator().manual_seed(10)
    x = torch.rand(200, 4, generator=gen, dtype=DTYPE) * torch.tensor([4.0, 20.0, 8 * math.pi, 20.0]) - torch.tensor(
        [2.0, 10.0, 4 * math.pi, 10.0])
    want = torch.exp(-((x[:, 2].abs() - math.pi) / 3) ** 2 - x[:, 0] ** 2)
    torch.testing.assert_close(cost(x), want, rtol=1e-12, atol=0)
    one_turn = x[:, 2].abs() <= math.pi
    torch.testing.assert_close(cost(x)[one_turn], mcpilco_cost()(x)[one_turn], rtol=1e-12, atol=0)
    up = torch.tensor([[0.0, 0.0, s * math.pi, 0.0] for s in (1.0, -1.0, 3.0, -3.0)], dtype=DTYPE)
    torch.testing.assert_close(mcpilco_cost()(up), torch.ones(4, dtype=DTYPE))  # wrapped: a turn-over is free
    r = cost(up)
    torch.testing.assert_close(r[:2], torch.ones(2, dtype=DTYPE))
    torch.testing.assert_close(r[2:], torch.full((2,), math.exp(-((2 * math.pi) / 3) ** 2), dtype=DTYPE))
    x = torch.tensor([[0.3, 1.0, 5.0, -1.0], [-0.2, 0.0, -7.5, 3.0]], dtype=DTYPE, requires_grad=True)
    assert torch.autograd.gradcheck(cost, (x,))


def test_angle_distance_reward_gradcheck_and_mixture():
    cost = mcpilco_cost()
    x = torch.tensor([[0.3, 1.0, 2.0, -1.0], [-0.2, 0.0, -2.5, 3.0]], dtype=DTYPE, requires_grad=True)
    assert torch.autograd.gradcheck(cost, (x,))
    task = ExpectedSaturatingReward.from_spec(cartpole_spec())
    mix = RewardMixture([cost, task], [0.5, 0.5])
    torch.testing.assert_close(mix(x), 0.5 * cost(x) + 0.5 * task(x), rtol=1e-14, atol=0)
    with pytest.raises(ValueError, match="no Gaussian expectation"):
        cost.expected(Gaussian(torch.zeros(4, dtype=DTYPE), torch.eye(4, dtype=DTYPE)))


def test_angle_distance_reward_refuses_bad_settings():
    with pytest.raises(ValueError, match="must be `4`"):
        AngleDistanceReward(4, (2,), [0.0, 0.0, 1.0], [1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="widths must be > 0"):
        AngleDistanceReward(4, (2,), [0.0] * 4, [1.0, 0.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="at least one finite"):
        AngleDistanceReward(4, (2,), [0.0] * 4, [math.inf] * 4)
    with pytest.raises(ValueError, match="target must be finite"):
        AngleDistanceReward(4, (2,), [math.nan, 0.0, 0.0, 0.0], [1.0, math.inf, 1.0, math.inf])
    with pytest.raises(ValueError, match="angle_dims"):
        AngleDistanceReward(4, (4,), [0.0] * 4, [1.0] * 4)
