"""The sparse GP (SGPR): equal to the exact GP when Z = X, close with fewer inducing inputs, and
moment matching through its cache against Monte Carlo."""

from __future__ import annotations

import gpytorch
import pytest
import torch

from qtl.gaussian import Gaussian
from qtl.kernels import SEKernelMoments
from qtl.models import DynamicsGP, SparseDynamicsGP
from qtl.models.dynamics_gp import exact_gp_settings
from qtl.policies import LinearPolicy, SquashedPolicy
from qtl.propagation import MomentMatching
from qtl.transfer import leave_one_out, task_compliance
from tests.helpers import quadratic_reward

DTYPE = torch.float64


@pytest.fixture(scope="module")
def exact(gp_factory) -> DynamicsGP:
    """E = 3 outputs, 6-D inputs (3-D state, one angle, 2 actions), n = 40, θ set."""
    return gp_factory(40, 3, 2, (1,), seed=7)


@pytest.fixture(scope="module")
def twin(exact) -> SparseDynamicsGP:
    """The sparse model with the training inputs as inducing inputs and the same θ."""
    return SparseDynamicsGP(exact.train_x, exact.train_y, exact.hyperparameters, inducing_points=exact.train_x)


def test_inducing_inputs_at_the_training_inputs_give_the_exact_gp(exact, twin):
    x = torch.randn(25, exact.input_dim, generator=torch.Generator().manual_seed(3), dtype=DTYPE)
    for noise in (False, True):
        mean, var = twin.predict(x, include_noise=noise)
        ref_mean, ref_var = exact.predict(x, include_noise=noise)
        torch.testing.assert_close(mean, ref_mean, rtol=1e-8, atol=1e-10)
        torch.testing.assert_close(var, ref_var, rtol=1e-6, atol=1e-10)
    exact.train(), twin.train()
    with torch.no_grad():  # Titsias' bound is the exact evidence when Z = X (the trace term vanishes)
        torch.testing.assert_close(twin.log_evidence(), exact.log_evidence(), rtol=1e-8, atol=1e-10)
    exact.eval(), twin.eval()
    torch.testing.assert_close(twin.hyperparameters.natural(), exact.hyperparameters.natural(), rtol=1e-12, atol=0)


def test_structured_evidence_equals_the_dense_cholesky_evidence(exact):
    # The O(n m²) bound against GPyTorch's dense n x n Cholesky of the same SGPR covariance, with
    # fewer inducing inputs than points (so the trace term is not 0): values and θ-gradients.
    sparse = SparseDynamicsGP(exact.train_x, exact.train_y, exact.hyperparameters, num_inducing=12,
                              generator=torch.Generator().manual_seed(4))
    sparse.train()
    fast = sparse.log_evidence()
    fast_grads = torch.autograd.grad(fast.sum(), list(sparse.parameters()))
    with exact_gp_settings():  # GPyTorch's dense n x n Cholesky of the same covariance
        dense = gpytorch.mlls.ExactMarginalLogLikelihood(sparse.likelihood, sparse)(
            sparse(*sparse.train_inputs), sparse.train_targets)
    dense_grads = torch.autograd.grad(dense.sum(), list(sparse.parameters()))
    sparse.eval()
    torch.testing.assert_close(fast, dense, rtol=1e-10, atol=1e-12)
    for got, want in zip(fast_grads, dense_grads, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-8, atol=1e-10)


def test_moment_matching_through_the_sparse_cache_equals_the_exact(exact, twin):
    gen = torch.Generator().manual_seed(5)
    state = Gaussian(0.3 * torch.randn(6, generator=gen, dtype=DTYPE), 0.2 * torch.eye(6, dtype=DTYPE))
    results = []
    for cache in (exact.posterior_cache(), twin.posterior_cache()):
        theta = cache.hyperparameters
        results.append(SEKernelMoments(cache.inputs, cache.beta, theta.lengthscales, theta.signal_variance,
                                       cache.K_inv)(state))
    torch.testing.assert_close(results[1].mean, results[0].mean, rtol=1e-7, atol=1e-10)
    torch.testing.assert_close(results[1].cov, results[0].cov, rtol=1e-6, atol=1e-10)
    torch.testing.assert_close(results[1].cross_cov, results[0].cross_cov, rtol=1e-6, atol=1e-10)


def test_fewer_inducing_inputs_after_fitting_predict_close_to_the_exact_gp(gp_factory):
    big = gp_factory(300, 2, 1, seed=2)
    exact = DynamicsGP(big.train_x, big.train_y)
    exact.fit(restarts=1, max_iter=60, generator=torch.Generator().manual_seed(0))
    sparse = SparseDynamicsGP(big.train_x, big.train_y, num_inducing=80, generator=torch.Generator().manual_seed(0))
    assert sparse.inducing_points.shape == (80, big.input_dim)
    sparse.fit(restarts=1, max_iter=60, generator=torch.Generator().manual_seed(0))
    x = big.train_x[:100] + 0.05 * torch.randn(100, big.input_dim, generator=torch.Generator().manual_seed(1))
    mean, var = sparse.predict(x)
    ref_mean, _ = exact.predict(x)
    spread = big.train_y.std(0)
    # 80 of 300 inputs: within 3 % of the targets' spread everywhere, 1 % in RMS (measured: 1.8 % and 0.4 %).
    assert ((mean - ref_mean).abs().max(0).values / spread < 0.03).all()
    assert ((mean - ref_mean).square().mean(0).sqrt() / spread < 0.01).all()
    assert (var >= 0).all() and (var.mean(0) < 0.05 * spread**2).all()


def test_moment_matching_through_a_sparse_model_against_monte_carlo(gp_factory, mc, posterior):
    big = gp_factory(120, 3, 2, (1,), seed=9)
    sparse = SparseDynamicsGP(big.train_x, big.train_y, big.hyperparameters, num_inducing=30,
                              generator=torch.Generator().manual_seed(4))
    cache = sparse.posterior_cache()
    assert cache.inputs.shape[0] == 30 and cache.K_inv.shape == (3, 30, 30)
    # The cache-form predictive (the MC reference below) is the model's own prediction.
    x_check = torch.randn(10, 6, generator=torch.Generator().manual_seed(8), dtype=DTYPE)
    for got, ref in zip(posterior(cache, x_check), sparse.predict(x_check), strict=True):
        torch.testing.assert_close(got, ref)
    gen = torch.Generator().manual_seed(6)
    state = Gaussian(0.4 * torch.randn(6, generator=gen, dtype=DTYPE), 0.5 * torch.eye(6, dtype=DTYPE))
    theta = cache.hyperparameters
    result = SEKernelMoments(cache.inputs, cache.beta, theta.lengthscales, theta.signal_variance, cache.K_inv)(state)
    x = state.sample(100_000, generator=gen)
    mean, var = posterior(cache, x)
    mc.assert_moments(result, x, mean, conditional_var=var)


def test_a_rollout_runs_through_a_sparse_model(gp_factory):
    big = gp_factory(80, 3, 1, (1,), seed=1)
    sparse = SparseDynamicsGP(big.train_x, big.train_y, big.hyperparameters, num_inducing=20,
                              generator=torch.Generator().manual_seed(0))
    policy = SquashedPolicy(LinearPolicy(4, 1, generator=torch.Generator().manual_seed(0)), 2.0)
    prop = MomentMatching(sparse, policy, quadratic_reward(3, (1,)), angle_dims=(1,))
    value = prop.expected_return(Gaussian(torch.zeros(3, dtype=DTYPE), 0.01 * torch.eye(3, dtype=DTYPE)), 5)
    value.backward()
    assert torch.isfinite(value) and all(torch.isfinite(p.grad).all() for p in policy.parameters())


def test_compliance_and_leave_one_out_of_a_sparse_model_use_its_exact_twin(exact, twin):
    for got, ref in zip(leave_one_out(twin), leave_one_out(exact), strict=True):
        torch.testing.assert_close(got, ref)
    assert task_compliance(exact, twin).value == pytest.approx(task_compliance(exact, exact).value, abs=1e-9)


def test_bad_inducing_inputs_are_refused(exact):
    with pytest.raises(ValueError, match="inducing_points must be"):
        SparseDynamicsGP(exact.train_x, exact.train_y, inducing_points=torch.zeros(5, 2, dtype=DTYPE))
    with pytest.raises(ValueError, match="num_inducing must be >= 1"):
        SparseDynamicsGP(exact.train_x, exact.train_y, num_inducing=0)
