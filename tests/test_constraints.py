"""qtl.constraints: p_t against Monte Carlo, survival and constrained return, their gradients, the relaxation."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
from scipy import stats

from qtl.constraints import (
    Constraint,
    bivariate_normal_cdf,
    constrained_return,
    crossed,
    gaussian_return,
    half_survival_step,
    inside_probability,
    lag_inside_probability,
    particle_return,
    soft_inside,
)
from qtl.gaussian import Gaussian

DTYPE = torch.float64
# Monte Carlo draws of each probability check: the standard error of a probability is at most 0.5/√N ≈ 8e-4.
DRAWS = 400_000
# A probability estimated from DRAWS indicator draws is accepted within 5 standard errors of the analytic one.
MC_Z = 5.0
CART = Constraint(dim=0, low=-2.4, high=2.4)
ONE_SIDED = (Constraint(dim=1, low=-0.5), Constraint(dim=1, high=0.3), Constraint(dim=0, low=10.0, high=11.0))


def mc_tolerance(p: torch.Tensor) -> torch.Tensor:
    """MC_Z standard errors of a probability estimated from DRAWS indicators, floored for p ≈ 0 or 1."""
    return MC_Z * (p * (1 - p) / DRAWS).sqrt() + 1e-6


@pytest.mark.parametrize("constraint", [CART, *ONE_SIDED])
def test_inside_probability_matches_monte_carlo(constraint):
    gen = torch.Generator().manual_seed(1)
    mean = torch.tensor([1.9, -0.1], dtype=DTYPE)
    cov = torch.tensor([[0.6, 0.2], [0.2, 0.3]], dtype=DTYPE)
    x = Gaussian(mean, cov).sample(DRAWS, generator=gen)
    p = inside_probability(constraint, mean, cov.diagonal())
    hard = soft_inside(constraint, x, temperature=0.0)  # the indicator 1[l ≤ x_d ≤ h]
    assert (p - hard.mean()).abs() <= mc_tolerance(p), (p, hard.mean())


def test_product_of_marginals_matches_monte_carlo_for_a_diagonal_covariance():
    # Two terminate bounds on different dimensions of a Gaussian with a diagonal Σ: independent, so the
    # product of the marginals (Safe-PILCO's p_t) is the joint probability of being within both.
    gen = torch.Generator().manual_seed(2)
    bounds = (Constraint(dim=0, low=-1.0, high=0.8), Constraint(dim=2, high=0.4))
    mean = torch.tensor([0.2, 5.0, 0.1], dtype=DTYPE)
    cov = torch.diag(torch.tensor([0.5, 2.0, 0.3], dtype=DTYPE))
    x = Gaussian(mean, cov).sample(DRAWS, generator=gen)
    p = inside_probability(bounds[0], mean, cov.diagonal()) * inside_probability(bounds[1], mean, cov.diagonal())
    joint = (soft_inside(bounds[0], x, 0.0) * soft_inside(bounds[1], x, 0.0)).mean()
    assert (p - joint).abs() <= mc_tolerance(p), (p, joint)


def test_inside_probability_keeps_its_precision_far_in_a_tail():
    # Both standardised bounds deep in the upper tail: Φ(b) − Φ(a) would cancel to 0, Φ(−a) − Φ(−b) does not.
    far = Constraint(dim=0, low=9.0, high=10.0)
    p = inside_probability(far, torch.zeros(1, dtype=DTYPE), torch.ones(1, dtype=DTYPE))
    exact = 0.5 * (math.erfc(9.0 / math.sqrt(2)) - math.erfc(10.0 / math.sqrt(2)))
    torch.testing.assert_close(p, torch.tensor(exact, dtype=DTYPE), rtol=1e-10, atol=0)


def test_survival_and_return_by_their_definitions():
    # Three steps, one terminate and one penalty bound: V = Σ_t S_t (r_t − w (1 − q_t)), S_t = Π_{τ≤t} p_τ.
    stop, cost = Constraint(dim=0, high=1.0), Constraint(dim=1, low=0.0, kind="penalty", weight=2.0)
    p = torch.tensor([0.9, 0.5, 0.2], dtype=DTYPE)
    q = torch.tensor([1.0, 0.7, 0.4], dtype=DTYPE)
    r = torch.tensor([0.1, 0.6, 0.9], dtype=DTYPE)
    value, survival = constrained_return([stop, cost], r, lambda c: p if c is stop else q)
    expected_s = torch.tensor([0.9, 0.45, 0.09], dtype=DTYPE)
    torch.testing.assert_close(survival, expected_s)
    torch.testing.assert_close(value, (expected_s * (r - 2.0 * (1 - q))).sum())
    penalty_only, none = constrained_return([cost], r, lambda c: q)
    assert none is None
    torch.testing.assert_close(penalty_only, (r - 2.0 * (1 - q)).sum())


@pytest.mark.parametrize(("batch", "dtype"),
                         list(itertools.product([(), (3,), (2, 4)], [torch.float64, torch.float32])))
def test_gaussian_return_broadcasts_over_leading_batch_dims(batch, dtype):
    # Restarts (and models) are leading batch dims: each batch entry equals its own unbatched evaluation.
    gen = torch.Generator().manual_seed(3)
    horizon, dim = 5, 2
    mean = torch.randn(*batch, horizon, dim, generator=gen, dtype=DTYPE).to(dtype)
    root = torch.randn(*batch, horizon, dim, dim, generator=gen, dtype=DTYPE).to(dtype)
    states = Gaussian(mean, root @ root.mT + 0.1 * torch.eye(dim, dtype=dtype))
    rewards = torch.rand(*batch, horizon, generator=gen, dtype=DTYPE).to(dtype)
    bounds = (CART, Constraint(dim=1, low=-1.0, kind="penalty", weight=0.5))
    value, survival = gaussian_return(bounds, rewards, states)
    assert value.shape == batch and survival.shape == (*batch, horizon) and value.dtype == dtype
    for index in itertools.product(*(range(b) for b in batch)):
        one = Gaussian(states.mean[index], states.cov[index])
        v, s = gaussian_return(bounds, rewards[index], one)
        torch.testing.assert_close(value[index], v, rtol=0, atol=0)
        torch.testing.assert_close(survival[index], s, rtol=0, atol=0)


def test_gradcheck_of_p_survival_and_return_wrt_mean_and_covariance():
    gen = torch.Generator().manual_seed(4)
    horizon = 4
    mean = (0.5 * torch.randn(horizon, 2, generator=gen, dtype=DTYPE)).requires_grad_()
    root = torch.randn(horizon, 2, 2, generator=gen, dtype=DTYPE)
    cov = (root @ root.mT + 0.2 * torch.eye(2, dtype=DTYPE)).requires_grad_()
    rewards = torch.rand(horizon, generator=gen, dtype=DTYPE).requires_grad_()
    bounds = (Constraint(dim=0, low=-1.0, high=1.5), Constraint(dim=1, high=0.7),
              Constraint(dim=1, low=-0.4, kind="penalty", weight=0.3))

    def p(m, c):
        return inside_probability(bounds[0], m, c.diagonal(dim1=-2, dim2=-1))

    def survival(m, c):
        return gaussian_return(bounds, rewards.detach(), Gaussian(m, c))[1]

    def value(m, c, r):
        return gaussian_return(bounds, r, Gaussian(m, c))[0]

    assert torch.autograd.gradcheck(p, (mean, cov))
    assert torch.autograd.gradcheck(survival, (mean, cov))
    assert torch.autograd.gradcheck(value, (mean, cov, rewards))


def test_gradcheck_of_the_relaxed_particle_return():
    gen = torch.Generator().manual_seed(5)
    x = (torch.randn(6, 3, 2, generator=gen, dtype=DTYPE) * 0.3).requires_grad_()  # P x H x D
    rewards = torch.rand(6, 3, generator=gen, dtype=DTYPE)
    bounds = (Constraint(dim=0, low=-0.3, high=0.4), Constraint(dim=1, low=-0.2, kind="penalty", weight=1.0))
    assert torch.autograd.gradcheck(lambda s: particle_return(bounds, rewards, s, temperature=0.1)[0], (x,))


def test_the_relaxed_indicator_tends_to_the_hard_one():
    x = torch.tensor([[-2.5], [-2.39], [0.0], [2.41], [3.0]], dtype=DTYPE)
    hard = soft_inside(CART, x, 0.0)
    torch.testing.assert_close(hard, torch.tensor([0.0, 1.0, 1.0, 0.0, 0.0], dtype=DTYPE))
    torch.testing.assert_close(soft_inside(CART, x, 1e-4), hard, rtol=0, atol=1e-12)
    # At the bound the sigmoid is one half: the relaxation is centred on it.
    torch.testing.assert_close(soft_inside(CART, torch.tensor([[2.4]], dtype=DTYPE), 0.05),
                               torch.tensor([0.5], dtype=DTYPE), rtol=0, atol=1e-12)


def test_half_survival_step_and_crossed():
    assert half_survival_step(None) is None
    assert half_survival_step(torch.tensor([0.9, 0.6, 0.5, 0.49, 0.1])) == 4  # t counts from 1 (x_1)
    assert half_survival_step(torch.tensor([0.9, 0.8])) is None
    with pytest.raises(ValueError, match="survival of one rollout"):
        half_survival_step(torch.ones(2, 3))
    states = np.array([[0.0, 0.0], [1.0, -0.6], [2.0, 0.0]])
    assert not crossed([CART], states)
    assert crossed([CART, ONE_SIDED[0]], states)  # x_1 is below dim 1's low
    assert not crossed([], states)


def test_from_config_reads_a_task_entry():
    c = Constraint.from_config({"dim": 2, "low": -1, "high": None, "kind": "penalty", "weight": 3})
    assert c == Constraint(dim=2, low=-1.0, high=None, kind="penalty", weight=3.0)
    assert isinstance(c.low, float) and isinstance(c.weight, float)
    assert Constraint.from_config({"dim": 0, "high": 1.0}) == Constraint(dim=0, high=1.0)


def test_the_bivariate_normal_cdf_matches_scipy():
    grid = [(h, k, rho) for rho in (-0.9999, -0.9, -0.3, 0.0, 0.5, 0.95, 0.999, 0.9999)
            for h in (-3.0, -0.2, 0.0, 1.5, 4.0) for k in (-2.5, 0.1, 2.0, 40.0)]
    h, k, rho = (torch.tensor(column, dtype=torch.float64) for column in zip(*grid, strict=True))
    got = bivariate_normal_cdf(h, k, rho)
    expected = torch.tensor([stats.multivariate_normal([0, 0], [[1, r], [r, 1]]).cdf([a, b]) for a, b, r in grid],
                            dtype=torch.float64)
    torch.testing.assert_close(got, expected, rtol=0, atol=1e-8)


def test_gradcheck_of_the_bivariate_normal_cdf():
    args = (torch.tensor([-0.7, 0.3, 1.2], dtype=torch.float64, requires_grad=True),
            torch.tensor([0.4, -1.1, 1.0], dtype=torch.float64, requires_grad=True),
            torch.tensor([0.2, -0.6, 0.97], dtype=torch.float64, requires_grad=True))
    assert torch.autograd.gradcheck(bivariate_normal_cdf, args)


@pytest.mark.parametrize("constraint", [Constraint(dim=0, low=-0.3, high=0.6), Constraint(dim=0, high=0.1)])
def test_the_pair_probability_matches_monte_carlo(constraint):
    # (x_{t−1,0}, x_{t,0}) from a 2-step joint Gaussian; P(both inside) against 400k draws.
    cov = torch.tensor([[0.2, 0.05, 0.17, 0.0], [0.05, 0.3, 0.0, 0.1], [0.17, 0.0, 0.25, 0.02],
                        [0.0, 0.1, 0.02, 0.4]], dtype=torch.float64)  # [x_{t−1}, x_t], 2-D each
    mean = torch.tensor([0.1, -0.2, 0.3, 0.0], dtype=torch.float64)
    before, after = Gaussian(mean[:2], cov[:2, :2]), Gaussian(mean[2:], cov[2:, 2:])
    p = lag_inside_probability(constraint, before, after, cov[:2, 2:])
    draws = torch.distributions.MultivariateNormal(mean, cov).sample((400_000,))
    both = (torch.as_tensor(constraint.contains(draws[:, :2].numpy()))
            & torch.as_tensor(constraint.contains(draws[:, 2:].numpy()))).double()
    assert (p - both.mean()).abs() <= mc_tolerance(p), (p, both.mean())


def test_the_markov_survival_is_the_product_for_uncorrelated_steps():
    stop = Constraint(dim=0, low=-0.5, high=0.4)
    gen = torch.Generator().manual_seed(0)
    mean = 0.3 * torch.randn(2, 5, 2, generator=gen, dtype=torch.float64)  # batch 2, H = 5, D = 2
    cov = torch.diag_embed(0.1 + torch.rand(2, 5, 2, generator=gen, dtype=torch.float64))
    rewards = torch.rand(2, 5, generator=gen, dtype=torch.float64)
    states = Gaussian(mean, cov)
    product = gaussian_return([stop], rewards, states)
    markov = gaussian_return([stop], rewards, states, lag_cov=torch.zeros_like(cov))
    torch.testing.assert_close(markov[1], product[1], rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(markov[0], product[0], rtol=1e-10, atol=1e-12)
