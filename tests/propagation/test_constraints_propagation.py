"""Constraints in both propagators: the survival-weighted return against particles, gradients, restarts, no change."""

from __future__ import annotations

import pytest
import torch

from qtl.constraints import Constraint
from qtl.gaussian import Gaussian
from qtl.policies import LinearPolicy
from qtl.propagation import MomentMatching, Particles
from tests.helpers import gradcheck_value_wrt_policy_and_start, quadratic_reward, squashed_rbf_parts
from tests.propagation.restarts import assert_restarts_equal_separate

DTYPE = torch.float64
MANY_PARTICLES = 100_000
# One step, no angles, a linear policy: moment matching's x_1 has the exact moments, but x_1 itself is not
# Gaussian; p_1 from its Gaussian is within this of the fraction of particles inside (100k: SE ≈ 1e-3).
SURVIVAL_ATOL = 0.01
# The return S_1 E[r(x_1)] against the particles' E[1[x_1 inside] r(x_1)]: moment matching takes the reward
# independent of being inside (as Safe-PILCO); on this model the two agree within 3 %.
RETURN_RTOL = 0.03
STOP = Constraint(dim=1, low=-0.9)  # bites at the first step only: the particles that leave do so there
BOUNDS = (Constraint(dim=0, low=-1.0, high=0.8), Constraint(dim=1, low=-0.7, kind="penalty", weight=0.5))


def linear_parts(gp_factory):
    """No angles, a linear policy: moment matching is exact for one step (the moments)."""
    gp = gp_factory(40, 2, 1, seed=21)
    policy = LinearPolicy(2, 1, weight=torch.tensor([[0.8, -0.5]], dtype=DTYPE), bias=torch.tensor([0.2], dtype=DTYPE))
    return gp, policy, quadratic_reward(2)


def start2() -> Gaussian:
    return Gaussian(torch.tensor([0.3, -0.4], dtype=DTYPE), torch.tensor([[0.3, 0.1], [0.1, 0.2]], dtype=DTYPE))


def test_survival_weighted_return_against_particles_with_hard_termination(gp_factory):
    gp, policy, reward = linear_parts(gp_factory)
    with torch.no_grad():
        mm = MomentMatching(gp, policy, reward, constraints=[STOP]).rollout(start2(), 1)
        hard = Particles(gp, policy, reward, constraints=[STOP], constraint_temperature=0.0,
                         num_particles=MANY_PARTICLES, include_noise=False, seed=3).rollout(start2(), 1)
    torch.testing.assert_close(mm.survival, hard.survival, rtol=0, atol=SURVIVAL_ATOL)
    torch.testing.assert_close(mm.value, hard.value, rtol=RETURN_RTOL, atol=0)
    torch.testing.assert_close(mm.value, mm.survival[0] * mm.rewards[0])


def test_the_product_survival_takes_the_steps_as_independent_and_so_is_pessimistic(gp_factory):
    # S_t = Π_{τ≤t} p_τ takes the steps' events as independent (Safe-PILCO); a trajectory's states are
    # positively correlated, so the particles' survival (hard indicator) lies above it.
    gp, policy, reward = linear_parts(gp_factory)
    with torch.no_grad():
        mm = MomentMatching(gp, policy, reward, constraints=[STOP], survival="product").rollout(start2(), 4)
        hard = Particles(gp, policy, reward, constraints=[STOP], constraint_temperature=0.0,
                         num_particles=20_000, include_noise=False, seed=3).rollout(start2(), 4)
    assert (mm.survival[1:] < mm.survival[:-1]).all()
    assert (mm.survival <= hard.survival + SURVIVAL_ATOL).all(), (mm.survival, hard.survival)


def test_no_constraints_leave_return_and_gradient_unchanged(gp_factory):
    # Without constraints the value is today's Σ_t E[r(x_t)], to the bit, and so is its gradient in ψ.
    gp, policy, reward = squashed_rbf_parts(gp_factory, 3, (1,), 4, seeds=(22, 23))
    start = Gaussian(torch.tensor([0.2, 0.5, -0.1], dtype=DTYPE), 0.05 * torch.eye(3, dtype=DTYPE))
    for propagator in (MomentMatching(gp, policy, reward, angle_dims=(1,)),
                       MomentMatching(gp, policy, reward, angle_dims=(1,), constraints=())):
        policy.zero_grad()
        rollout = propagator.rollout(start, 2)
        assert rollout.survival is None
        rollout.value.backward(retain_graph=True)
        grads = [p.grad.clone() for p in policy.parameters()]
        policy.zero_grad()
        states = rollout.states
        plain = reward.expected(Gaussian(states.mean[1:], states.cov[1:])).sum(-1)
        plain.backward()
        assert torch.equal(rollout.value.detach(), plain.detach())
        assert all(torch.equal(g, p.grad) for g, p in zip(grads, policy.parameters(), strict=True))
    particles = Particles(gp, policy, reward, angle_dims=(1,), num_particles=50, seed=1)
    with torch.no_grad():
        paths, _ = particles.trajectories(start, 2)
        assert torch.equal(particles.rollout(start, 2).value, reward(paths[..., 1:, :]).sum(-1).mean(-1))


@pytest.mark.parametrize("propagator", ["moment_matching", "moment_matching_product", "particles"])
def test_gradcheck_of_the_constrained_return_wrt_policy_and_start(gp_factory, propagator):
    # Through p_t and the pairs' Φ₂ (moment matching) or the relaxed indicator (particles, τ = 0.1), a terminate and a
    # penalty bound.
    gp, policy, reward = linear_parts(gp_factory)
    bounds = (Constraint(dim=0, low=-0.2, high=0.5), Constraint(dim=1, high=0.0, kind="penalty", weight=0.3))
    if propagator.startswith("moment_matching"):
        made = MomentMatching(gp, policy, reward, constraints=bounds,
                              survival="product" if propagator.endswith("product") else "markov")
    else:
        made = Particles(gp, policy, reward, num_particles=8, seed=2, constraints=bounds, constraint_temperature=0.1)
    assert gradcheck_value_wrt_policy_and_start(policy, lambda s: made.rollout(s, 3).value, start2())


@pytest.mark.parametrize("propagator", ["moment_matching", "particles"])
def test_constrained_restarts_equal_separate_rollouts(gp_factory, propagator):
    gp, policy, reward = linear_parts(gp_factory)
    if propagator == "moment_matching":
        def make(p):
            return MomentMatching(gp, p, reward, constraints=BOUNDS)
    else:
        def make(p):
            return Particles(gp, p, reward, num_particles=16, seed=4, constraints=BOUNDS)
    assert_restarts_equal_separate(make, policy, start2(), 3)


def test_a_penalty_alone_subtracts_its_expected_cost(gp_factory):
    gp, policy, reward = linear_parts(gp_factory)
    cost = Constraint(dim=0, high=0.5, kind="penalty", weight=2.0)
    with torch.no_grad():
        plain = MomentMatching(gp, policy, reward).rollout(start2(), 3)
        costed = MomentMatching(gp, policy, reward, constraints=[cost]).rollout(start2(), 3)
    mean, std = plain.states.mean[1:, 0], plain.states.cov[1:, 0, 0].sqrt()
    outside = 1 - torch.special.ndtr((0.5 - mean) / std)
    assert costed.survival is None
    torch.testing.assert_close(costed.value, plain.value - 2.0 * outside.sum())


def test_a_negative_temperature_is_refused(gp_factory):
    gp, policy, reward = linear_parts(gp_factory)
    with pytest.raises(Exception, match="constraint_temperature must be >= 0"):
        Particles(gp, policy, reward, constraints=[STOP], constraint_temperature=-1.0)


def drifting_parts(gp_factory):
    """A squashed RBF policy on a 3-D state with an angle, and a bound on x_0 its states cross over several steps."""
    gp, policy, reward = squashed_rbf_parts(gp_factory, 3, (1,), 4, seeds=(22, 23))
    start = Gaussian(torch.tensor([0.2, 0.5, -0.1], dtype=DTYPE), 0.05 * torch.eye(3, dtype=DTYPE))
    return gp, policy, reward, start


@pytest.mark.parametrize("parts", ["linear", "drifting"])
def test_the_markov_survival_follows_the_particles_where_the_product_falls_away(gp_factory, parts):
    # Each consecutive pair's bivariate Gaussian (the step's lag-one covariance) in place of independent steps: the
    # particles' survival (hard termination, 20k) within SURVIVAL_ATOL + the one-step Gaussian error, at every step.
    if parts == "linear":
        gp, policy, reward = linear_parts(gp_factory)
        start, stop, angles, horizon = start2(), STOP, (), 10
    else:
        gp, policy, reward, start = drifting_parts(gp_factory)
        angles, horizon = (1,), 8
        with torch.no_grad():
            free = MomentMatching(gp, policy, reward, angle_dims=angles).rollout(start, horizon)
        # A bound the predicted x_0 crosses gradually: at the median of its mean's path.
        stop = Constraint(dim=0, high=float(free.states.mean[1:, 0].median()))
    with torch.no_grad():
        markov = MomentMatching(gp, policy, reward, angle_dims=angles, constraints=[stop]).rollout(start, horizon)
        product = MomentMatching(gp, policy, reward, angle_dims=angles, constraints=[stop],
                                 survival="product").rollout(start, horizon)
        hard = Particles(gp, policy, reward, angle_dims=angles, constraints=[stop], constraint_temperature=0.0,
                         num_particles=20_000, include_noise=False, seed=3).rollout(start, horizon)
    markov_gap = (markov.survival - hard.survival).abs()
    product_gap = (product.survival - hard.survival).abs()
    assert float(markov_gap.max()) < 0.05, (markov.survival, hard.survival)
    assert float(product_gap[-1]) > 2 * float(markov_gap[-1]) + 0.02, (product.survival, markov.survival)
