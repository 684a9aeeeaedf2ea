"""The sparse GP (SGPR): equal to the exact GP when Z = X, close with fewer inducing inputs, its
K_mm jitter in bound and prediction alike, and moment matching through its cache against Monte Carlo."""

from __future__ import annotations

import math

import gpytorch
import pytest
import torch
from torch import Tensor

from qtl.gaussian import Gaussian
from qtl.kernels import SEKernelMoments
from qtl.models import DynamicsGP, GPHyperparameters, SparseDynamicsGP
from qtl.models.exact_settings import exact_gp_settings
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
    """The sparse model with the training inputs as inducing inputs, the same θ and no jitter on K_mm."""
    return SparseDynamicsGP(exact.train_x, exact.train_y, exact.hyperparameters, inducing_points=exact.train_x,
                            jitter=0.0)


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


def _dense_sgpr(model: SparseDynamicsGP, x: Tensor, jitter: float) -> tuple[Tensor, Tensor, Tensor]:
    """Predictive mean and variance `E x k` at ``x``, and K_nm (K_mm + δI)⁻¹ K_mn `E x n x n`, from the SGPR
    formulas with plain dense solves (Titsias 2009; δ = ``jitter`` · α²): the reference for the model's own."""
    theta, z, kernel = model.hyperparameters, model.inducing_points, model.scale_kernel
    e, m = model.num_outputs, z.shape[0]
    with torch.no_grad():
        k_mm = kernel(z.expand(e, *z.shape)).to_dense() + (jitter * theta.signal_variance)[:, None, None] * torch.eye(
            m, dtype=DTYPE)
        k_mn = kernel(z.expand(e, *z.shape), model.train_x.expand(e, *model.train_x.shape)).to_dense()
        k_mx = kernel(z.expand(e, *z.shape), x.expand(e, *x.shape)).to_dense()
    noise = theta.noise_variance[:, None, None]
    sigma = noise * k_mm + k_mn @ k_mn.mT  # σ² Σ
    y = model.train_y.T[..., None]  # E x n x 1
    mean = (k_mx.mT @ torch.linalg.solve(sigma, k_mn @ y)).squeeze(-1)
    var = (theta.signal_variance[:, None] - (k_mx * torch.linalg.solve(k_mm, k_mx)).sum(-2)
           + (k_mx * torch.linalg.solve(sigma / noise, k_mx)).sum(-2))
    return mean, var, k_mn.mT @ torch.linalg.solve(k_mm, k_mn)


def test_the_jitter_is_on_k_mm_in_the_bound_and_in_the_prediction(exact):
    # A jitter large enough to move everything (1e-2 of α²): the model's prediction, and the covariance its
    # bound is made of, are the SGPR's with K_mm + δI, checked against dense solves of the formulas.
    jitter = 1e-2
    sparse = SparseDynamicsGP(exact.train_x, exact.train_y, exact.hyperparameters, num_inducing=15,
                              generator=torch.Generator().manual_seed(2), jitter=jitter)
    assert sparse.jitter == jitter
    x = torch.randn(20, exact.input_dim, generator=torch.Generator().manual_seed(3), dtype=DTYPE)
    mean, var, q_nn = _dense_sgpr(sparse, x, jitter)
    got_mean, got_var = sparse.predict(x)
    torch.testing.assert_close(got_mean, mean.T, rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(got_var, var.T, rtol=1e-6, atol=1e-10)
    _, _, q_plain = _dense_sgpr(sparse, x, 0.0)
    assert (q_nn - q_plain).abs().max() > 1e-3 * float(exact.hyperparameters.signal_variance.min())  # δ shows
    sparse.train()
    with torch.no_grad():
        torch.testing.assert_close(sparse.covar_module(sparse.train_x).to_dense(), q_nn, rtol=1e-8, atol=1e-12)
        # The bound with δ minus the bound without it, against the same difference by hand (the priors cancel).
        plain = SparseDynamicsGP(exact.train_x, exact.train_y, exact.hyperparameters,
                                 inducing_points=sparse.inducing_points, jitter=0.0)
        plain.train()
        n = exact.train_x.shape[0]

        def bound(q: Tensor) -> Tensor:
            cov = q + exact.hyperparameters.noise_variance[:, None, None] * torch.eye(n, dtype=DTYPE)
            y = exact.train_y.T
            fit = torch.distributions.MultivariateNormal(torch.zeros_like(y), covariance_matrix=cov).log_prob(y)
            trace = (exact.hyperparameters.signal_variance * n - q.diagonal(dim1=-2, dim2=-1).sum(-1))
            return (fit - 0.5 * trace / exact.hyperparameters.noise_variance) / n

        torch.testing.assert_close(sparse.log_evidence() - plain.log_evidence(), bound(q_nn) - bound(q_plain),
                                   rtol=1e-6, atol=1e-10)


@pytest.fixture(scope="module")
def crowded() -> tuple[Tensor, Tensor, GPHyperparameters]:
    """Inputs `400 x 3`, targets `400 x 2` and θ where 150 inducing inputs crowd the space at the lengthscales.

    As on a fitted mountain car: two inputs span a few lengthscales, the third is irrelevant (lengthscale 10
    over [-1, 1]), and the noise is ~1e-7 of α², so K_mm is singular to working precision.
    """
    gen = torch.Generator().manual_seed(0)
    x = torch.cat([torch.rand(400, 2, generator=gen, dtype=DTYPE) * torch.tensor([1.0, 0.1], dtype=DTYPE),
                   2 * torch.rand(400, 1, generator=gen, dtype=DTYPE) - 1], -1)
    y = torch.stack([0.1 * torch.sin(3 * x[:, 0]) + x[:, 1], 0.5 * x[:, 1] + 0.01 * x[:, 2]], -1)
    theta = GPHyperparameters(lengthscales=torch.tensor([[0.6, 0.06, 10.0]] * 2, dtype=DTYPE),
                              signal_variance=torch.tensor([1e-2, 1e-3], dtype=DTYPE),
                              noise_variance=torch.tensor([1e-9, 1e-10], dtype=DTYPE))
    return x, y, theta


def test_the_jitter_keeps_the_cached_variance_accurate_when_inducing_inputs_crowd(crowded):
    # The cache form α² − k (K_mm⁻¹ − Σ⁻¹) kᵀ (what moment matching and particles use) against the whitened
    # form α² − ‖L⁻¹k‖² + ‖L_B⁻¹L⁻¹k‖² (dense, no K_mm⁻¹ formed), both with the model's δ. Without a jitter
    # the cache holds entries ~1e14 and its variance is off by thousands of σ_ε² (measured 4.1e3, 4.5e3);
    # with the default (1e-6 of α²), by ~1e-2 σ_ε².
    x, y, theta = crowded
    x_check = x[:50] + 0.01 * torch.randn(50, 3, generator=torch.Generator().manual_seed(1), dtype=DTYPE)
    errors = {}
    for jitter in (0.0, None):
        kwargs = {} if jitter is None else {"jitter": jitter}
        model = SparseDynamicsGP(x, y, theta, num_inducing=150, generator=torch.Generator().manual_seed(1), **kwargs)
        delta = model.jitter * theta.signal_variance
        z, kernel = model.inducing_points, model.scale_kernel
        with torch.no_grad():
            k_mm = kernel(z.expand(2, *z.shape)).to_dense() + delta[:, None, None] * torch.eye(150, dtype=DTYPE)
            k_mn = kernel(z.expand(2, *z.shape), x.expand(2, *x.shape)).to_dense()
            k_mx = kernel(z.expand(2, *z.shape), x_check.expand(2, *x_check.shape)).to_dense()
        chol = torch.linalg.cholesky(k_mm)
        a = torch.linalg.solve_triangular(chol, k_mn, upper=False) / theta.noise_variance.sqrt()[:, None, None]
        chol_b = torch.linalg.cholesky(torch.eye(150, dtype=DTYPE) + a @ a.mT)
        v1 = torch.linalg.solve_triangular(chol, k_mx, upper=False)
        v2 = torch.linalg.solve_triangular(chol_b, v1, upper=False)
        whitened = theta.signal_variance[:, None] - v1.square().sum(-2) + v2.square().sum(-2)
        _, var = model.predict(x_check)
        errors[jitter] = ((var.T - whitened.clamp_min(0)).abs().amax(-1) / theta.noise_variance).max()
        if jitter == 0.0:
            assert model.posterior_cache().K_inv.abs().max() > 1e12  # the problem is as ill-conditioned as meant
    assert errors[0.0] > 100 and errors[None] < 0.1, errors


def test_moment_matching_through_a_crowded_sparse_model_against_monte_carlo(crowded, mc, posterior):
    x, y, theta = crowded
    model = SparseDynamicsGP(x, y, theta, num_inducing=150, generator=torch.Generator().manual_seed(1))
    cache = model.posterior_cache()
    state = Gaussian(torch.tensor([0.5, 0.05, 0.0], dtype=DTYPE), torch.diag(torch.tensor([0.01, 1e-4, 0.1],
                                                                                             dtype=DTYPE)))
    result = SEKernelMoments(cache.inputs, cache.beta, theta.lengthscales, theta.signal_variance, cache.K_inv)(state)
    gen = torch.Generator().manual_seed(2)
    samples = state.sample(100_000, generator=gen)
    mean, var = posterior(cache, samples)
    assert (var > -1e-3 * theta.noise_variance).all()  # the cache's variance is a variance (no cancellation)
    assert math.isfinite(float(result.cov.sum()))
    mc.assert_moments(result, samples, mean, conditional_var=var)


def test_bad_inducing_inputs_are_refused(exact):
    with pytest.raises(ValueError, match="inducing_points must be"):
        SparseDynamicsGP(exact.train_x, exact.train_y, inducing_points=torch.zeros(5, 2, dtype=DTYPE))
    with pytest.raises(ValueError, match="num_inducing must be >= 1"):
        SparseDynamicsGP(exact.train_x, exact.train_y, num_inducing=0)
    with pytest.raises(ValueError, match="jitter must be >= 0"):
        SparseDynamicsGP(exact.train_x, exact.train_y, num_inducing=5, jitter=-1e-6)
