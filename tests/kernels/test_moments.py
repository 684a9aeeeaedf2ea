"""SE-kernel moment matching (PILCO gp0/gp2): Monte Carlo, delta inputs, batching, gradients, PSD."""

from __future__ import annotations

import itertools

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from qtl.gaussian import Gaussian
from qtl.kernels import SEKernelMoments
from qtl.kernels.engine import DEFAULT_ENGINE, FORMULATIONS, Engine
from qtl.kernels.moments import inverse_and_half_logdet
from qtl.models import GPPosteriorCache
from tests.test_features import assert_formulations_agree, assert_rel_close, random_state

DTYPE = torch.float64
NUM_SAMPLES = 100_000


@pytest.fixture(params=FORMULATIONS)
def engine(request) -> Engine:
    """Each formulation of the moments in turn (torch exp sums)."""
    return Engine(moments=request.param)


def gp_moments(cache: GPPosteriorCache, engine: Engine = DEFAULT_ENGINE) -> SEKernelMoments:
    theta = cache.hyperparameters
    return SEKernelMoments(cache.inputs, cache.beta, theta.lengthscales, theta.signal_variance, cache.K_inv,
                           engine=engine)


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
def test_gp_moments_against_monte_carlo(model, mc, posterior, cov_factory, scale, engine):
    cache = model.posterior_cache()
    gen = torch.Generator().manual_seed(int(10 * scale))
    state = Gaussian(0.5 * torch.randn(6, generator=gen, dtype=DTYPE), cov_factory(6, scale, gen))
    result = gp_moments(cache, engine)(state)
    x = state.sample(NUM_SAMPLES, generator=gen)
    mean, var = posterior(cache, x)
    # Law of total variance: cov Δ = cov(E[Δ | x]) + E[var(Δ | x)], the outputs independent given x.
    mc.assert_moments(result, x, mean, conditional_var=var)
    torch.testing.assert_close(state.cov @ result.gain, result.cross_cov)


def test_delta_input_equals_gp_prediction(model, engine):
    x = torch.tensor([0.3, -0.2, 0.5, 0.1, -0.7, 0.4], dtype=DTYPE)
    result = gp_moments(model.posterior_cache(), engine)(Gaussian(x, torch.zeros(6, 6, dtype=DTYPE)))
    ref_mean, ref_var = model.predict(x[None])
    torch.testing.assert_close(result.mean, ref_mean[0])
    torch.testing.assert_close(result.cov, torch.diag(ref_var[0]), atol=1e-12, rtol=0)


def test_without_model_variance_is_the_regressor_mean(model, engine):
    # gp2: a delta input gives f(x) and zero covariance.
    cache = model.posterior_cache()
    theta = cache.hyperparameters
    moments = SEKernelMoments(cache.inputs, cache.beta, theta.lengthscales, theta.signal_variance, engine=engine)
    x = torch.tensor([0.3, -0.2, 0.5, 0.1, -0.7, 0.4], dtype=DTYPE)
    result = moments(Gaussian(x, torch.zeros(6, 6, dtype=DTYPE)))
    torch.testing.assert_close(result.mean, model.predict(x[None])[0][0])
    assert result.cov.abs().max() < 1e-12


def test_batched_states_and_stacked_models(gp_factory, cov_factory, engine):
    models = [gp_factory(25, 2, 1, seed=s) for s in (1, 2)]
    caches = [m.posterior_cache() for m in models]
    stacked = SEKernelMoments(
        torch.stack([c.inputs for c in caches]),
        torch.stack([c.beta for c in caches]),
        torch.stack([c.hyperparameters.lengthscales for c in caches]),
        torch.stack([c.hyperparameters.signal_variance for c in caches]),
        torch.stack([c.K_inv for c in caches]),
        engine=engine,
    )
    gen = torch.Generator().manual_seed(3)
    means = torch.randn(4, 1, 3, generator=gen, dtype=DTYPE)  # 4 states x 2 models
    covs = cov_factory(3, 0.7, gen, batch=(4, 1))
    batched = stacked(Gaussian(means, covs))
    assert batched.cov.shape == (4, 2, 2, 2)
    for i, j in itertools.product(range(4), range(2)):
        single = gp_moments(caches[j], engine)(Gaussian(means[i, 0], covs[i, 0]))
        torch.testing.assert_close(batched.mean[i, j], single.mean)
        torch.testing.assert_close(batched.cov[i, j], single.cov)
        torch.testing.assert_close(batched.cross_cov[i, j], single.cross_cov)


def test_gradcheck_wrt_input_distribution(gp_factory, engine):
    cache = gp_factory(8, 2, 1, seed=4).posterior_cache()
    moments = gp_moments(cache, engine)
    gen = torch.Generator().manual_seed(5)
    mean = torch.randn(3, generator=gen, dtype=DTYPE).requires_grad_()
    root = (0.5 * torch.randn(3, 3, generator=gen, dtype=DTYPE)).requires_grad_()

    def fn(m, r):
        out = moments(Gaussian(m, r @ r.T))
        return out.mean, out.cov, out.cross_cov

    assert torch.autograd.gradcheck(fn, (mean, root))


@pytest.mark.parametrize("moments", FORMULATIONS)
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(1e-3, 5.0), shift=st.floats(0.0, 4.0))
def test_covariance_is_psd(model, psd, cov_factory, seed, scale, shift, moments):
    gen = torch.Generator().manual_seed(seed)
    state = Gaussian(shift * torch.randn(6, generator=gen, dtype=DTYPE), cov_factory(6, scale, gen))
    result = gp_moments(model.posterior_cache(), Engine(moments=moments))(state)
    psd(result.cov)
    joint = torch.cat(
        [torch.cat([state.cov, result.cross_cov], -1), torch.cat([result.cross_cov.T, result.cov], -1)],
        -2,
    )
    psd(joint)


# --- The fused formulation against the reference one (qtl.kernels.Engine), values and gradients. ---


def regressor_tensors(caches, requires_grad: bool) -> dict[str, torch.Tensor]:
    """inputs, beta, lengthscales, signal variance (and K_inv) of one cache or of caches stacked as `M`."""
    def stacked(get):
        return torch.stack([get(c) for c in caches]) if len(caches) > 1 else get(caches[0])

    tensors = {
        "inputs": stacked(lambda c: c.inputs),
        "beta": stacked(lambda c: c.beta),
        "lengthscales": stacked(lambda c: c.hyperparameters.lengthscales),
        "signal_variance": stacked(lambda c: c.hyperparameters.signal_variance),
    }
    tensors = {k: v.detach().clone().requires_grad_(requires_grad) for k, v in tensors.items()}
    tensors["K_inv"] = stacked(lambda c: c.K_inv)
    return tensors


@pytest.mark.parametrize(
    ("models", "state_batch", "with_variance"),
    [(1, (), True), (1, (3,), True), (2, (3, 1), True), (1, (), False), (1, (3,), False), (2, (3, 1), False)],
)
def test_formulations_agree(gp_factory, models, state_batch, with_variance):
    """Values and gradients (w.r.t. the input distribution and the regressor's tensors, as a policy's ψ) of the
    fused and the reference formulation; restarts `R` as the state batch, stacked models `M` as the regressor's."""
    caches = [gp_factory(30, 3, 1, (1,), seed=7 + m).posterior_cache() for m in range(models)]
    tensors = regressor_tensors(caches, requires_grad=True)
    K_inv = tensors.pop("K_inv") if with_variance else None
    mean, root = random_state(5, state_batch, seed=models + len(state_batch))

    def moments(engine, m, r, *params):
        out = SEKernelMoments(*params, K_inv=K_inv, engine=engine)(Gaussian(m, r @ r.mT))
        return out.mean, out.cov, out.cross_cov, out.gain

    params = tuple(tensors[k] for k in ("inputs", "beta", "lengthscales", "signal_variance"))
    assert_formulations_agree(moments, (mean, root, *params))


def test_mean_cov_gain_is_call_without_cross_cov(model, engine):
    moments = gp_moments(model.posterior_cache(), engine)
    state = Gaussian(torch.linspace(-1, 1, 6, dtype=DTYPE), 0.3 * torch.eye(6, dtype=DTYPE))
    full = moments(state)
    for got, want in zip(moments.mean_cov_gain(state), (full.mean, full.cov, full.gain), strict=True):
        assert torch.equal(got, want)
    with pytest.raises(ValueError, match="6-D input"):
        moments.mean_cov_gain(Gaussian(torch.zeros(5, dtype=DTYPE), torch.eye(5, dtype=DTYPE)))


@pytest.mark.parametrize("batch", [(), (4,), (2, 3)])
def test_inverse_and_half_logdet(batch):
    gen = torch.Generator().manual_seed(len(batch))
    root = torch.randn(*batch, 4, 4, generator=gen, dtype=DTYPE)
    mat = (root @ root.mT + torch.eye(4, dtype=DTYPE)).requires_grad_()
    inverse, half_logdet = inverse_and_half_logdet(mat)
    assert torch.equal(inverse, inverse.mT)
    assert_rel_close(inverse, torch.linalg.inv(mat))
    assert_rel_close(half_logdet, 0.5 * torch.logdet(mat))
    # The closed-form backward against autograd through Cholesky factor, solve and log-determinant.
    weights = torch.randn(*batch, 4, 4, generator=gen, dtype=DTYPE), torch.randn(batch, generator=gen, dtype=DTYPE)
    (got,) = torch.autograd.grad((inverse * weights[0]).sum() + (half_logdet * weights[1]).sum(), mat)
    chol = torch.linalg.cholesky(mat)
    plain = torch.cholesky_solve(torch.eye(4, dtype=DTYPE).expand_as(mat), chol)
    plain_half_logdet = torch.diagonal(chol, dim1=-2, dim2=-1).log().sum(-1)
    (want,) = torch.autograd.grad((plain * weights[0]).sum() + (plain_half_logdet * weights[1]).sum(), mat)
    assert_rel_close(got, want)
    assert torch.autograd.gradcheck(lambda r: inverse_and_half_logdet(r @ r.mT + torch.eye(4, dtype=DTYPE)),
                                    (root[..., :, :].clone().requires_grad_(),))


def test_inverse_and_half_logdet_refuses_indefinite_matrices():
    # Policy search treats a LinAlgError as an invalid ψ: the fused factorisation must still raise it.
    with pytest.raises(torch.linalg.LinAlgError):
        inverse_and_half_logdet(torch.diag(torch.tensor([1.0, -1.0], dtype=DTYPE)))
