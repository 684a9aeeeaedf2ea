"""SE-kernel moment matching (PILCO gp0/gp2): Monte Carlo, delta inputs, batching, gradients, PSD."""

from __future__ import annotations

import itertools

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from qtl.gaussian import Gaussian
from qtl.kernels import SEKernelMoments
from qtl.models import GPPosteriorCache

DTYPE = torch.float64
NUM_SAMPLES = 100_000


def gp_moments(cache: GPPosteriorCache) -> SEKernelMoments:
    theta = cache.hyperparameters
    return SEKernelMoments(cache.inputs, cache.beta, theta.lengthscales, theta.signal_variance, cache.K_inv)


@pytest.fixture(scope="module")
def model(gp_factory):
    """E = 3 outputs on a 6-D input (3-D state with 1 angle → 4 features, 2 actions), n = 40."""
    return gp_factory(40, 3, 2, (1,), seed=11)


def test_posterior_reference_matches_dynamics_gp(model, posterior):
    # The Monte Carlo references below evaluate the GP through `posterior`: check it once.
    x = torch.randn(20, model.input_dim, generator=torch.Generator().manual_seed(1), dtype=DTYPE)
    mean, var = posterior(model.posterior_cache(), x)
    ref_mean, ref_var = model.predict(x)
    torch.testing.assert_close(mean, ref_mean)
    torch.testing.assert_close(var, ref_var)


@pytest.mark.parametrize("scale", [0.2, 1.0, 2.5])
def test_gp_moments_against_monte_carlo(model, mc, posterior, cov_factory, scale):
    cache = model.posterior_cache()
    gen = torch.Generator().manual_seed(int(10 * scale))
    state = Gaussian(0.5 * torch.randn(6, generator=gen, dtype=DTYPE), cov_factory(6, scale, gen))
    result = gp_moments(cache)(state)
    x = state.sample(NUM_SAMPLES, generator=gen)
    mean, var = posterior(cache, x)
    # Law of total variance: cov Δ = cov(E[Δ | x]) + E[var(Δ | x)], the outputs independent given x.
    mc.assert_moments(result, x, mean, conditional_var=var)
    torch.testing.assert_close(state.cov @ result.gain, result.cross_cov)


def test_delta_input_equals_gp_prediction(model):
    x = torch.tensor([0.3, -0.2, 0.5, 0.1, -0.7, 0.4], dtype=DTYPE)
    result = gp_moments(model.posterior_cache())(Gaussian(x, torch.zeros(6, 6, dtype=DTYPE)))
    ref_mean, ref_var = model.predict(x[None])
    torch.testing.assert_close(result.mean, ref_mean[0])
    torch.testing.assert_close(result.cov, torch.diag(ref_var[0]), atol=1e-12, rtol=0)


def test_without_model_variance_is_the_regressor_mean(model):
    # gp2: a delta input gives f(x) and zero covariance.
    cache = model.posterior_cache()
    theta = cache.hyperparameters
    moments = SEKernelMoments(cache.inputs, cache.beta, theta.lengthscales, theta.signal_variance)
    x = torch.tensor([0.3, -0.2, 0.5, 0.1, -0.7, 0.4], dtype=DTYPE)
    result = moments(Gaussian(x, torch.zeros(6, 6, dtype=DTYPE)))
    torch.testing.assert_close(result.mean, model.predict(x[None])[0][0])
    assert result.cov.abs().max() < 1e-12


def test_batched_states_and_stacked_models(gp_factory, cov_factory):
    models = [gp_factory(25, 2, 1, seed=s) for s in (1, 2)]
    caches = [m.posterior_cache() for m in models]
    stacked = SEKernelMoments(
        torch.stack([c.inputs for c in caches]),
        torch.stack([c.beta for c in caches]),
        torch.stack([c.hyperparameters.lengthscales for c in caches]),
        torch.stack([c.hyperparameters.signal_variance for c in caches]),
        torch.stack([c.K_inv for c in caches]),
    )
    gen = torch.Generator().manual_seed(3)
    means = torch.randn(4, 1, 3, generator=gen, dtype=DTYPE)  # 4 states x 2 models
    covs = cov_factory(3, 0.7, gen, batch=(4, 1))
    batched = stacked(Gaussian(means, covs))
    assert batched.cov.shape == (4, 2, 2, 2)
    for i, j in itertools.product(range(4), range(2)):
        single = gp_moments(caches[j])(Gaussian(means[i, 0], covs[i, 0]))
        torch.testing.assert_close(batched.mean[i, j], single.mean)
        torch.testing.assert_close(batched.cov[i, j], single.cov)
        torch.testing.assert_close(batched.cross_cov[i, j], single.cross_cov)


def test_gradcheck_wrt_input_distribution(gp_factory):
    cache = gp_factory(8, 2, 1, seed=4).posterior_cache()
    moments = gp_moments(cache)
    gen = torch.Generator().manual_seed(5)
    mean = torch.randn(3, generator=gen, dtype=DTYPE).requires_grad_()
    root = (0.5 * torch.randn(3, 3, generator=gen, dtype=DTYPE)).requires_grad_()

    def fn(m, r):
        out = moments(Gaussian(m, r @ r.T))
        return out.mean, out.cov, out.cross_cov

    assert torch.autograd.gradcheck(fn, (mean, root))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(1e-3, 5.0), shift=st.floats(0.0, 4.0))
def test_covariance_is_psd(model, psd, cov_factory, seed, scale, shift):
    gen = torch.Generator().manual_seed(seed)
    state = Gaussian(shift * torch.randn(6, generator=gen, dtype=DTYPE), cov_factory(6, scale, gen))
    result = gp_moments(model.posterior_cache())(state)
    psd(result.cov)
    joint = torch.cat(
        [torch.cat([state.cov, result.cross_cov], -1), torch.cat([result.cross_cov.T, result.cov], -1)],
        -2,
    )
    psd(joint)
