"""GP predictive terms at points: values and gradients against plain autograd, gradcheck, the GP posterior."""

from __future__ import annotations

import itertools

import pytest
import torch
from torch import Tensor

from qtl.kernels import gp_predictive

DTYPE = torch.float64


def reference(z: Tensor, data: Tensor, beta: Tensor, K_inv: Tensor, signal_variance: Tensor) -> tuple[Tensor, Tensor]:
    """Mean k β and variance α² − k K⁻¹ kᵀ by plain autograd-traced torch, `... x E x P` (Eq. 1-2)."""
    sq_dist = (z[..., :, None, :] - data[..., None, :, :]).square().sum(-1)  # ... x E x P x n
    kern = signal_variance[..., None, None] * torch.exp(-0.5 * sq_dist)
    mean = (kern * beta[..., None, :]).sum(-1)
    var = signal_variance[..., None] - ((kern @ K_inv) * kern).sum(-1)
    return mean, var


def random_inputs(batch: tuple[int, ...], num_out: int, points: int, n: int, dim: int, seed: int) -> tuple[Tensor, ...]:
    """Points, data (over ℓ), β, a symmetric positive definite K⁻¹ and α², in float64."""
    gen = torch.Generator().manual_seed(seed)
    z = 0.7 * torch.randn(*batch, num_out, points, dim, generator=gen, dtype=DTYPE)
    data = 0.7 * torch.randn(*batch, num_out, n, dim, generator=gen, dtype=DTYPE)
    beta = torch.randn(*batch, num_out, n, generator=gen, dtype=DTYPE)
    root = torch.randn(*batch, num_out, n, n, generator=gen, dtype=DTYPE)
    K_inv = root @ root.mT / n + 0.1 * torch.eye(n, dtype=DTYPE)
    signal_variance = 0.5 + torch.rand(*batch, num_out, generator=gen, dtype=DTYPE)
    return z, data, beta, K_inv, signal_variance


@pytest.mark.parametrize(("batch", "points"), list(itertools.product([(), (2,), (2, 3)], [1, 5])))
def test_value_and_gradient_equal_plain_autograd(batch, points):
    z, data, beta, K_inv, signal_variance = random_inputs(batch, 3, points, 7, 4, seed=len(batch) + points)
    z_fast, z_ref = z.clone().requires_grad_(), z.clone().requires_grad_()
    mean, var = gp_predictive(z_fast, data, data.square().sum(-1), beta, K_inv, signal_variance)
    expected_mean, expected_var = reference(z_ref, data, beta, K_inv, signal_variance)
    assert mean.shape == var.shape == (*batch, 3, points)
    torch.testing.assert_close(mean, expected_mean, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(var, expected_var, rtol=1e-12, atol=1e-12)
    gen = torch.Generator().manual_seed(9)
    weight_mean, weight_var = (torch.randn(mean.shape, generator=gen, dtype=DTYPE) for _ in range(2))
    (mean * weight_mean + var * weight_var).sum().backward()
    (expected_mean * weight_mean + expected_var * weight_var).sum().backward()
    torch.testing.assert_close(z_fast.grad, z_ref.grad, rtol=1e-10, atol=1e-12)


def test_gradcheck_wrt_points():
    z, data, beta, K_inv, signal_variance = random_inputs((2,), 2, 3, 5, 3, seed=4)
    data_sq = data.square().sum(-1)
    assert torch.autograd.gradcheck(
        lambda points: gp_predictive(points, data, data_sq, beta, K_inv, signal_variance),
        (z.requires_grad_(),),
    )


def test_far_from_the_data_the_prior_is_returned():
    # Far from the data k → 0: the mean is 0 and the variance the prior α² (the clamp keeps exp finite).
    z, data, beta, K_inv, signal_variance = random_inputs((), 2, 3, 4, 2, seed=5)
    with torch.no_grad():
        mean, var = gp_predictive(z + 1e3, data, data.square().sum(-1), beta, K_inv, signal_variance)
    torch.testing.assert_close(mean, torch.zeros_like(mean))
    torch.testing.assert_close(var, signal_variance[:, None].expand_as(var))


def test_equals_the_gp_posterior(gp_factory, posterior):
    # The inputs a propagator hands it (data and points over ℓ) give the GP's latent posterior.
    cache = gp_factory(30, 2, 1, seed=8).posterior_cache()
    theta = cache.hyperparameters
    x = torch.randn(6, cache.inputs.shape[-1], generator=torch.Generator().manual_seed(1), dtype=DTYPE)
    inv_ls = theta.lengthscales.reciprocal()[:, None, :]  # E x 1 x D
    data = cache.inputs * inv_ls
    mean, var = gp_predictive(x * inv_ls, data, data.square().sum(-1), cache.beta, cache.K_inv, theta.signal_variance)
    expected_mean, expected_var = posterior(cache, x)
    torch.testing.assert_close(mean.T, expected_mean)
    torch.testing.assert_close(var.T, expected_var)
