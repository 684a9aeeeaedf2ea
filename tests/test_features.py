"""Angle features: the project convention, exact moments (PILCO gTrig), gradients, PSD."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from qtl.envs.rewards import augment_angles
from qtl.features import AngleFeatures, trig_moments
from qtl.gaussian import Gaussian
from qtl.kernels.engine import FORMULATIONS, Engine

DTYPE = torch.float64
NUM_SAMPLES = 100_000


@pytest.fixture(params=FORMULATIONS)
def engine(request) -> Engine:
    """Each formulation of the moments in turn (torch exp sums)."""
    return Engine(moments=request.param)


@pytest.mark.parametrize("angle_dims", [(), (2,), (0, 3), (3, 1)])
def test_matches_env_convention(angle_dims):
    x = torch.randn(7, 4, generator=torch.Generator().manual_seed(0), dtype=DTYPE)
    ours = AngleFeatures(4, angle_dims)(x)
    theirs = augment_angles(x.numpy(), angle_dims)
    np.testing.assert_allclose(ours.numpy(), theirs, rtol=0, atol=1e-14)


@pytest.mark.parametrize(("angle_dims", "scale"), list(itertools.product([(2,), (0, 3), (3, 1)], [0.3, 2.0])))
def test_moments_against_monte_carlo(mc, cov_factory, angle_dims, scale, engine):
    gen = torch.Generator().manual_seed(len(angle_dims) + int(10 * scale))
    mean = torch.randn(4, generator=gen, dtype=DTYPE)
    state = Gaussian(mean, cov_factory(4, scale, gen))
    features = AngleFeatures(4, angle_dims)
    result = features.moments(state, engine)
    x = state.sample(NUM_SAMPLES, generator=gen)
    mc.assert_moments(result, x, features(x))
    # The gain is Σ⁻¹ cov[x, y] (Stein's lemma).
    torch.testing.assert_close(state.cov @ result.gain, result.cross_cov)


def test_no_angles_is_identity(engine):
    cov = torch.eye(3, dtype=DTYPE) * 0.5
    result = AngleFeatures(3).moments(Gaussian(torch.ones(3, dtype=DTYPE), cov), engine)
    torch.testing.assert_close(result.cov, cov)
    torch.testing.assert_close(result.gain, torch.eye(3, dtype=DTYPE))


def test_delta_input_gives_point_features(engine):
    x = torch.tensor([0.1, -0.4, 2.5], dtype=DTYPE)
    features = AngleFeatures(3, (2, 0))
    result = features.moments(Gaussian(x, torch.zeros(3, 3, dtype=DTYPE)), engine)
    torch.testing.assert_close(result.mean, features(x))
    assert result.cov.abs().max() < 1e-15


def test_batched_equals_per_item(cov_factory, engine):
    gen = torch.Generator().manual_seed(3)
    means = torch.randn(2, 3, 4, generator=gen, dtype=DTYPE)
    covs = cov_factory(4, 1.0, gen, batch=(2, 3))
    features = AngleFeatures(4, (1, 2))
    batched = features.moments(Gaussian(means, covs), engine)
    for i, j in itertools.product(range(2), range(3)):
        single = features.moments(Gaussian(means[i, j], covs[i, j]), engine)
        torch.testing.assert_close(batched.mean[i, j], single.mean)
        torch.testing.assert_close(batched.cov[i, j], single.cov)
        torch.testing.assert_close(batched.cross_cov[i, j], single.cross_cov)


def test_gradcheck(engine):
    gen = torch.Generator().manual_seed(4)
    mean = torch.randn(3, generator=gen, dtype=DTYPE, requires_grad=True)
    root = (0.5 * torch.randn(3, 3, generator=gen, dtype=DTYPE)).requires_grad_()
    features = AngleFeatures(3, (0, 2))

    def moments(m, r):
        out = features.moments(Gaussian(m, r @ r.T), engine)
        return out.mean, out.cov, out.cross_cov

    assert torch.autograd.gradcheck(moments, (mean, root))


@pytest.mark.parametrize("moments", FORMULATIONS)
@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(1e-3, 5.0))
def test_covariance_is_psd(psd, cov_factory, seed, scale, moments):
    engine = Engine(moments=moments)
    gen = torch.Generator().manual_seed(seed)
    state = Gaussian(3 * torch.randn(5, generator=gen, dtype=DTYPE), cov_factory(5, scale, gen))
    result = AngleFeatures(5, (0, 2, 4)).moments(state, engine)
    psd(result.cov)
    # The joint [x, y] must be PSD too, since the rollout chains through it.
    joint = torch.cat(
        [torch.cat([state.cov, result.cross_cov], -1), torch.cat([result.cross_cov.T, result.cov], -1)],
        -2,
    )
    psd(joint)


def test_trig_moments_of_one_angle_closed_form(engine):
    mean, var = torch.tensor([0.7], dtype=DTYPE), torch.tensor([[0.4]], dtype=DTYPE)
    out_mean, out_cov, _ = trig_moments(mean, var, engine)
    damp = torch.exp(-var[0, 0] / 2)
    torch.testing.assert_close(out_mean, damp * torch.cat([mean.sin(), mean.cos()]))
    # var(sin θ) = ½(1 − e^{−2σ²} cos 2μ) − E[sin θ]².
    expected = 0.5 * (1 - torch.exp(-2 * var[0, 0]) * torch.cos(2 * mean[0])) - out_mean[0] ** 2
    torch.testing.assert_close(out_cov[0, 0], expected)


def test_trig_moments_stay_finite_for_huge_variances(engine):
    """Regression: exp(−σ²)·expm1(σ²) overflowed to inf · 0 = NaN once σ² passed ~709."""
    mean = torch.tensor([0.3, -1.0], dtype=torch.float64, requires_grad=True)
    cov = torch.tensor([[800.0, 500.0], [500.0, 900.0]], dtype=torch.float64, requires_grad=True)
    out_mean, out_cov, gain = trig_moments(mean, cov, engine)
    assert torch.isfinite(out_mean).all() and torch.isfinite(out_cov).all() and torch.isfinite(gain).all()
    # Far spread angles: sin and cos are uncorrelated with variance ½ each.
    torch.testing.assert_close(out_cov, 0.5 * torch.eye(4, dtype=torch.float64), atol=1e-12, rtol=0)
    (out_cov.sum() + out_mean.sum()).backward()
    assert torch.isfinite(mean.grad).all() and torch.isfinite(cov.grad).all()


# --- The fused formulation against the reference one (qtl.kernels.Engine), values and gradients. ---

REFERENCE_RTOL = 1e-12  # relative to the largest entry of each compared tensor


def assert_rel_close(got: torch.Tensor, want: torch.Tensor, what: str = "", rtol: float = REFERENCE_RTOL) -> None:
    """max |got − want| <= rtol · max |want| (shapes equal)."""
    assert got.shape == want.shape, f"{what}: shape {tuple(got.shape)} != {tuple(want.shape)}"
    err, scale = (got - want).abs().max().item(), want.abs().max().item()
    assert err <= rtol * scale, f"{what}: max error {err:.3e} > {rtol:g} x {scale:.3e}"


def random_state(dim: int, batch: tuple[int, ...], seed: int, scale: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """A mean `batch x D` and a covariance root `batch x D x D` (cov = root rootᵀ), both requiring grad."""
    gen = torch.Generator().manual_seed(seed)
    mean = torch.randn(*batch, dim, generator=gen, dtype=DTYPE).requires_grad_()
    root = (scale * torch.randn(*batch, dim, dim, generator=gen, dtype=DTYPE) / dim**0.5).requires_grad_()
    return mean, root


def assert_formulations_agree(fn, inputs: tuple[torch.Tensor, ...], seed: int = 0) -> None:
    """``fn(engine, *inputs)`` (a tuple of tensors) is the same, to REFERENCE_RTOL in values and in the gradients
    w.r.t. every input that requires grad, under the fused and the reference formulation."""
    got = fn(Engine(moments="fused"), *inputs)
    want = fn(Engine(moments="reference"), *inputs)
    gen = torch.Generator().manual_seed(seed)
    weights = [torch.randn(w.shape, generator=gen, dtype=DTYPE) for w in want]
    for i, (g, w) in enumerate(zip(got, want, strict=True)):
        assert_rel_close(g, w, f"output {i}")
    leaves = [t for t in inputs if t.requires_grad]

    def gradients(outputs):
        loss = sum((o * w).sum() for o, w in zip(outputs, weights, strict=True))
        return torch.autograd.grad(loss, leaves, allow_unused=True)

    for i, (g, w) in enumerate(zip(gradients(got), gradients(want), strict=True)):
        if w is None:
            assert g is None or not g.any(), f"gradient {i}: expected none"
        else:
            assert_rel_close(g, w, f"gradient {i}")


@pytest.mark.parametrize(("num", "batch", "scale"), list(itertools.product([1, 2, 3], [(), (3,), (2, 3)], [0.3, 3.0])))
def test_trig_moments_formulations_agree(num, batch, scale):
    mean, root = random_state(num, batch, seed=num + 10 * len(batch), scale=scale)
    assert_formulations_agree(lambda e, m, r: trig_moments(m, r @ r.mT, e), (mean, root))


def test_trig_moments_formulations_agree_at_zero_covariance():
    # σ_ij = 0 exactly (a diagonal Σ, one zero variance): the expm1 branches meet there, the gradients
    # must too. Σ = (A + Aᵀ)/2, so that the gradient is that of a symmetric Σ (as in a rollout).
    mean = torch.tensor([0.4, -1.2, 2.0], dtype=DTYPE, requires_grad=True)
    cov_param = torch.diag(torch.tensor([0.3, 0.0, 1.5], dtype=DTYPE)).requires_grad_()
    assert_formulations_agree(lambda e, m, a: trig_moments(m, 0.5 * (a + a.mT), e), (mean, cov_param))


@pytest.mark.parametrize(
    ("angle_dims", "batch"), list(itertools.product([(2,), (0, 3), (3, 1), (0, 1, 2, 3)], [(), (3,), (2, 3)]))
)
def test_angle_moments_formulations_agree(angle_dims, batch):
    features = AngleFeatures(4, angle_dims)
    mean, root = random_state(4, batch, seed=len(angle_dims) + len(batch))

    def moments(engine, m, r):
        out = features.moments(Gaussian(m, r @ r.mT), engine)
        return out.mean, out.cov, out.cross_cov, out.gain

    assert_formulations_agree(moments, (mean, root))

