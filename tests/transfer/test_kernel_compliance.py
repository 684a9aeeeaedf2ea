"""Task compliance after Lazaric et al. (Eq. 14): the source GP as the kernel estimate of P(S | τ)."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from qtl.models import DynamicsGP
from qtl.transfer.compliance import (
    COMPLIANCES,
    DEFAULT_COMPLIANCE,
    KernelCompliance,
    compliance_function,
    kernel_compliance,
    scott_bandwidth,
    task_compliance,
)

DTYPE = torch.float64
# Predicting at a GP's own training inputs is what "identical data" means here.
SAME_INPUTS = pytest.mark.filterwarnings("ignore:The input matches the stored training data")
# Monte Carlo checks: the estimate must lie within this many standard errors of its expectation.
MC_STANDARD_ERRORS = 4.0


def _with_data(model: DynamicsGP, inputs: torch.Tensor, deltas: torch.Tensor) -> DynamicsGP:
    """A GP on other tuples with the model's θ: the target side only reads its tuples."""
    return DynamicsGP(inputs, deltas, model.hyperparameters)


def _predictive_sd(model: DynamicsGP) -> torch.Tensor:
    """`E`: the mean over the model's own inputs of its noisy predictive standard deviation."""
    _, var = model.predict(model.train_x, include_noise=True)
    return var.sqrt().mean(0)


# ---- the definition -----------------------------------------------------------------------------
@SAME_INPUTS
def test_terms_are_the_source_density_relative_to_its_mode(gp_factory) -> None:
    source, target = gp_factory(40, 2, 1, seed=0), gp_factory(30, 2, 1, seed=1, lengthscale=1.0)
    result = kernel_compliance(source, target, bandwidth="none")
    assert isinstance(result, KernelCompliance)
    assert result.log_kernel.shape == (30, 2) and result.probabilities.shape == (30,)
    assert result.log_kernel.dtype == result.probabilities.dtype == DTYPE

    mean, var = source.predict(target.train_x, include_noise=True)
    normal = torch.distributions.Normal(mean, var.sqrt())
    expected = normal.log_prob(target.train_y) - normal.log_prob(mean)  # log p_S(Δ) − log p_S(mode)
    torch.testing.assert_close(result.log_kernel, expected, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(result.probabilities, expected.sum(-1).exp(), rtol=1e-10, atol=1e-14)
    assert ((result.probabilities > 0) & (result.probabilities <= 1)).all()
    assert result.value == pytest.approx(result.probabilities.mean().item(), abs=1e-14)
    # A tuple the source predicts exactly has compliance 1.
    exact = kernel_compliance(source, _with_data(source, target.train_x, mean), bandwidth="none")
    torch.testing.assert_close(exact.probabilities, torch.ones(30, dtype=DTYPE), rtol=0, atol=1e-12)


@pytest.mark.parametrize("state_dim", [1, 2, 3])
def test_tuples_of_the_source_task_give_two_to_the_minus_half_e(gp_factory, state_dim: int) -> None:
    # Fresh tuples of the source task itself: Δ drawn from the source's noisy predictive at new inputs.
    # Then λ = exp(−χ²_E / 2): E[λ] = 2^(−E/2), E[λ²] = 3^(−E/2).
    source = gp_factory(40, state_dim, 1, seed=0)
    n = 3000
    gen = torch.Generator().manual_seed(7)
    inputs = torch.randn(n, source.input_dim, generator=gen, dtype=DTYPE)
    mean, var = source.predict(inputs, include_noise=True)
    deltas = mean + var.sqrt() * torch.randn(n, state_dim, generator=gen, dtype=DTYPE)
    result = kernel_compliance(source, _with_data(source, inputs, deltas), bandwidth="none")

    expected = 2.0 ** (-state_dim / 2)
    standard_error = math.sqrt((3.0 ** (-state_dim / 2) - expected**2) / n)
    assert abs(result.value - expected) < MC_STANDARD_ERRORS * standard_error, (result.value, expected)


@SAME_INPUTS
def test_identical_data_give_the_expected_compliance_of_a_gp_on_its_own_tuples(gp_factory) -> None:
    # Source = target, data drawn from the GP's own prior y ~ N(0, K + σ²I) per output. At its training
    # inputs the residual is r_i = σ² [K_y⁻¹y]_i, Gaussian with variance s_i² = σ⁴ [K_y⁻¹]_ii, so
    # E[λ_i] = Π_a (1 + s_ia² / v_ia)^(−1/2), v_ia the noisy predictive variance there.
    template = gp_factory(30, 2, 1, seed=0)
    inputs, theta = template.train_x, template.hyperparameters
    k_inv = template.posterior_cache().K_inv  # E x n x n, (K + σ²I)⁻¹; independent of y
    root = torch.linalg.cholesky(torch.linalg.inv(k_inv))  # E x n x n
    _, var = template.predict(inputs, include_noise=True)  # n x E; independent of y
    residual_var = theta.noise_variance.square()[:, None] * torch.diagonal(k_inv, dim1=-2, dim2=-1)  # E x n
    expected = (1.0 + residual_var.T / var).rsqrt().prod(-1).mean().item()
    assert expected > 2.0 ** (-theta.num_outputs / 2)  # its own tuples: above fresh tuples of the task

    gen = torch.Generator().manual_seed(11)
    values = []
    for _ in range(150):
        y = (root @ torch.randn(theta.num_outputs, inputs.shape[0], 1, generator=gen, dtype=DTYPE)).squeeze(-1).T
        model = DynamicsGP(inputs, y, theta)
        values.append(kernel_compliance(model, model, bandwidth="none").value)
    values_t = torch.tensor(values, dtype=DTYPE)
    standard_error = values_t.std().item() / math.sqrt(len(values))
    assert abs(values_t.mean().item() - expected) < MC_STANDARD_ERRORS * standard_error, (values_t.mean(), expected)


# ---- behaviour under a change of the target's dynamics ------------------------------------------
@SAME_INPUTS
def test_a_shift_beyond_the_predictive_spread_lowers_compliance(gp_factory) -> None:
    source = gp_factory(40, 2, 1, seed=0)
    same = kernel_compliance(source, source, bandwidth="none").value
    shifted = _with_data(source, source.train_x, source.train_y + 3.0 * _predictive_sd(source))
    far = kernel_compliance(source, shifted, bandwidth="none").value
    assert same > 0.5
    # Three predictive standard deviations in each of two outputs: λ ≈ exp(−9) per tuple.
    assert far < 0.05 * same, (same, far)


@SAME_INPUTS
@pytest.mark.parametrize("state_dim", [1, 3])
def test_compliance_falls_monotonically_with_the_shift(gp_factory, state_dim: int) -> None:
    source = gp_factory(40, state_dim, 1, seed=2)
    sd = _predictive_sd(source)
    values = [
        kernel_compliance(source, _with_data(source, source.train_x, source.train_y + c * sd), bandwidth="none").value
        for c in (0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0)
    ]
    for nearer, farther in itertools.pairwise(values):
        assert farther < nearer, values
    # A shift of the opposite sign lowers it as well.
    opposite = _with_data(source, source.train_x, source.train_y - sd)
    assert kernel_compliance(source, opposite, bandwidth="none").value < values[0]


def test_invariant_to_the_order_of_the_tuples(gp_factory) -> None:
    source, target = gp_factory(40, 3, 1, seed=0), gp_factory(35, 3, 1, seed=4, lengthscale=1.0)
    result = kernel_compliance(source, target)
    order = torch.randperm(35, generator=torch.Generator().manual_seed(5))
    permuted = kernel_compliance(source, _with_data(target, target.train_x[order], target.train_y[order]))
    assert permuted.value == pytest.approx(result.value, rel=1e-12)
    torch.testing.assert_close(permuted.probabilities, result.probabilities[order], rtol=1e-12, atol=1e-14)


# ---- resolution ---------------------------------------------------------------------------------
def test_resolution_widens_the_kernel_by_the_documented_floor(gp_factory) -> None:
    source, target = gp_factory(40, 2, 1, seed=0), gp_factory(30, 2, 1, seed=1, lengthscale=1.0)
    rho = 0.2
    result = kernel_compliance(source, target, bandwidth="none", resolution=rho)
    assert result.resolution == rho
    mean, var = source.predict(target.train_x, include_noise=True)
    floor = rho**2 * target.train_y.var(dim=0, correction=0)
    torch.testing.assert_close(
        result.log_kernel, -0.5 * (target.train_y - mean).square() / (var + floor), rtol=1e-10, atol=1e-12
    )
    assert result.value > kernel_compliance(source, target, bandwidth="none").value
    assert kernel_compliance(source, target, resolution=1e4).value == pytest.approx(1.0, abs=1e-6)


# ---- the bandwidth: Scott's rule on the source's Δ ----------------------------------------------
def test_scott_bandwidth_is_scipys_gaussian_kde_bandwidth() -> None:
    scipy_stats = pytest.importorskip("scipy.stats")
    gen = torch.Generator().manual_seed(3)
    for m, num_outputs in ((50, 1), (200, 2), (400, 4)):
        deltas = torch.randn(m, num_outputs, generator=gen, dtype=DTYPE) * torch.linspace(0.1, 3.0, num_outputs)
        kde = scipy_stats.gaussian_kde(deltas.T.numpy(), bw_method="scott")
        want = torch.as_tensor(kde.covariance, dtype=DTYPE).diagonal().sqrt()  # σ̂_a × scipy's Scott factor
        torch.testing.assert_close(scott_bandwidth(deltas), want, rtol=1e-12, atol=0)
    assert (scott_bandwidth(deltas[:1]) == 0).all()  # one tuple: no spread to smooth with


def test_bandwidth_widens_the_predictive_by_the_source_bandwidth(gp_factory) -> None:
    source, target = gp_factory(40, 2, 1, seed=0), gp_factory(30, 2, 1, seed=1, lengthscale=1.0)
    result = kernel_compliance(source, target)  # bandwidth="scott", the default
    h = scott_bandwidth(source.train_y)
    torch.testing.assert_close(result.bandwidth, h, rtol=0, atol=0)
    mean, var = source.predict(target.train_x, include_noise=True)
    torch.testing.assert_close(
        result.log_kernel, -0.5 * (target.train_y - mean).square() / (var + h.square()), rtol=1e-10, atol=1e-12
    )
    assert result.value > kernel_compliance(source, target, bandwidth="none").value
    assert (kernel_compliance(source, target, bandwidth="none").bandwidth == 0).all()
    # The width is the source's: other target tuples leave it unchanged.
    other = _with_data(target, target.train_x, 5.0 * target.train_y)
    torch.testing.assert_close(kernel_compliance(source, other).bandwidth, h, rtol=0, atol=0)


def test_bandwidth_is_the_kernel_density_smoothing_of_the_source_predictive(gp_factory) -> None:
    # λ_ia = [N(0, h²) * N(μ, v)](Δ) / its value at the mode: the Gaussian smoothing of the source's
    # predictive by the kernel, checked by averaging N(Δ; μ + ε, v) over ε ~ N(0, h²).
    source, target = gp_factory(40, 2, 1, seed=0), gp_factory(6, 2, 1, seed=1, lengthscale=1.0)
    result = kernel_compliance(source, target)
    mean, var = source.predict(target.train_x, include_noise=True)  # 6 x 2 each
    h = result.bandwidth
    draws = 200_000
    eps = h * torch.randn(draws, 1, 2, generator=torch.Generator().manual_seed(9), dtype=DTYPE)
    smoothed = torch.distributions.Normal(mean + eps, var.sqrt()).log_prob(target.train_y).exp()  # draws x 6 x 2
    at_mode = (2 * math.pi * (var + h.square())).rsqrt()  # the smoothed density's peak, N(μ; μ, v + h²)
    estimate = smoothed.mean(0) / at_mode
    standard_error = smoothed.std(0) / math.sqrt(draws) / at_mode
    deviation = (estimate - result.log_kernel.exp()).abs()
    assert (deviation < MC_STANDARD_ERRORS * standard_error).all(), (deviation / standard_error)


@SAME_INPUTS
def test_with_the_bandwidth_compliance_falls_monotonically_with_the_shift(gp_factory) -> None:
    source = gp_factory(40, 3, 1, seed=2)
    h = scott_bandwidth(source.train_y)
    values = [
        kernel_compliance(source, _with_data(source, source.train_x, source.train_y + c * h)).value
        for c in (0.0, 0.5, 1.0, 2.0, 4.0)
    ]
    for nearer, farther in itertools.pairwise(values):
        assert farther < nearer, values
    assert 0.05 < values[2] < 0.95, values  # a shift of one bandwidth is not saturated


# ---- selection and input checks -----------------------------------------------------------------
def test_selection_by_name_keeps_the_default() -> None:
    assert DEFAULT_COMPLIANCE == "kernel"
    assert compliance_function() is kernel_compliance
    assert compliance_function("likelihood_ratio") is task_compliance
    assert compliance_function("kernel") is kernel_compliance
    assert set(COMPLIANCES) == {"likelihood_ratio", "kernel"}
    with pytest.raises(ValueError, match="unknown task compliance 'lazaric'"):
        compliance_function("lazaric")


def _forbid_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make any prediction fail the test: the checks must come before any work."""

    def fail(*_args, **_kwargs):
        raise AssertionError("kernel_compliance did work before validating its arguments")

    monkeypatch.setattr(DynamicsGP, "predict", fail)


def test_mismatched_dimensions_raise(gp_factory, monkeypatch) -> None:
    source, target = gp_factory(10, 2, 1, seed=0), gp_factory(10, 3, 1, seed=1)
    _forbid_work(monkeypatch)
    with pytest.raises(ValueError, match="source GP has D=3 inputs and E=2 outputs, target GP has D=4 inputs"):
        kernel_compliance(source, target)


def test_bad_bandwidth_raises(gp_factory, monkeypatch) -> None:
    source, target = gp_factory(10, 2, 1, seed=0), gp_factory(10, 2, 1, seed=1)
    _forbid_work(monkeypatch)
    with pytest.raises(ValueError, match="bandwidth must be one of scott, none, got 'silverman'"):
        kernel_compliance(source, target, bandwidth="silverman")


@pytest.mark.parametrize("resolution", [-0.1, float("nan"), float("inf")])
def test_bad_resolution_raises(gp_factory, monkeypatch, resolution: float) -> None:
    source, target = gp_factory(10, 2, 1, seed=0), gp_factory(10, 2, 1, seed=1)
    _forbid_work(monkeypatch)
    with pytest.raises(ValueError, match="resolution must be finite and >= 0"):
        kernel_compliance(source, target, resolution=resolution)


def _modelled(model: DynamicsGP, outputs: list[int]) -> DynamicsGP:
    """``model``'s data and θ of ``outputs`` only, as the loop fits it under speed integration."""
    return DynamicsGP(model.train_x, model.train_y[:, outputs], model.hyperparameters.select(torch.tensor(outputs)),
                      outputs=outputs, state_dim=model.num_outputs)


def test_compliance_is_computed_on_the_modelled_outputs(gp_factory):
    # Without a bandwidth each output's kernel factor depends on that output alone: the modelled models' factors
    # are the full models' factors of those outputs, and Λ their product's mean.
    source, target = gp_factory(30, 4, 1, (2,), seed=41), gp_factory(20, 4, 1, (2,), seed=42)
    outputs = [1, 3]
    full = kernel_compliance(source, target, bandwidth="none", resolution=0.1)
    cut = kernel_compliance(_modelled(source, outputs), _modelled(target, outputs), bandwidth="none", resolution=0.1)
    torch.testing.assert_close(cut.log_kernel, full.log_kernel[:, outputs], rtol=1e-10, atol=1e-12)
    assert cut.value == pytest.approx(float(full.log_kernel[:, outputs].sum(-1).exp().mean()), rel=1e-10)
    with pytest.raises(ValueError, match=r"modelled outputs \(source \[1, 3\], target \[0, 2\]\)"):
        kernel_compliance(_modelled(source, outputs), _modelled(target, [0, 2]))


def test_compliance_leaves_out_an_output_one_side_modelled_as_deterministic(gp_factory):
    # The target found output 1's Δ constant: Λ is computed on output 3, the one both GPs learn.
    source, target = gp_factory(30, 4, 1, (2,), seed=41), gp_factory(20, 4, 1, (2,), seed=42)
    both = kernel_compliance(_modelled(source, [1, 3]), _modelled(target, [1, 3]), bandwidth="none", resolution=0.1)
    fixed = DynamicsGP(target.train_x, target.train_y[:, [3]], target.hyperparameters.select(torch.tensor([3])),
                       outputs=[3], state_dim=4, constant_outputs=[1], constant_delta=torch.zeros(1))
    one = kernel_compliance(_modelled(source, [1, 3]), fixed, bandwidth="none", resolution=0.1)
    torch.testing.assert_close(one.log_kernel, both.log_kernel[:, 1:], rtol=1e-10, atol=1e-12)
