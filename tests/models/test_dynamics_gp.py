"""DynamicsGP: fit quality, batching, θ seam, persistence, exact solves and input checks."""

from __future__ import annotations

import itertools
import math

import pytest
import torch
from linear_operator.utils.errors import NotPSDError

from qtl import health
from qtl.models import DynamicsGP, GPHyperparameters, exact_gp_settings
from qtl.models.dynamics_gp import NOISE_VARIANCE_MIN
from qtl.models.gp_evidence import FIT_RESUMES


def smooth_function(x: torch.Tensor) -> torch.Tensor:
    """A known smooth map `n x 3` -> `n x 2`."""
    return torch.stack(
        [torch.sin(2.0 * x[:, 0]) + 0.5 * x[:, 1], torch.cos(x[:, 1]) * x[:, 2]], dim=-1
    )


def make_data(n: int, noise_std: float, seed: int, dtype=torch.float64):
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=gen, dtype=dtype) * 4.0 - 2.0
    y = smooth_function(x) + noise_std * torch.randn(n, 2, generator=gen, dtype=dtype)
    return x, y


def random_theta(num_outputs: int, input_dim: int, seed: int) -> GPHyperparameters:
    gen = torch.Generator().manual_seed(seed)
    return GPHyperparameters(
        lengthscales=0.5 + torch.rand(num_outputs, input_dim, generator=gen, dtype=torch.float64),
        signal_variance=0.5 + torch.rand(num_outputs, generator=gen, dtype=torch.float64),
        noise_variance=1e-3 + 1e-2 * torch.rand(num_outputs, generator=gen, dtype=torch.float64),
    )


def test_recovers_smooth_function_and_noise_level():
    noise_std = 0.05
    x, y = make_data(200, noise_std, seed=0)
    model = DynamicsGP(x, y)
    model.fit(restarts=2, max_iter=60, generator=torch.Generator().manual_seed(0))
    x_test, _ = make_data(500, 0.0, seed=1)
    mean, var = model.predict(x_test)
    rmse = ((mean - smooth_function(x_test)) ** 2).mean(dim=0).sqrt()
    # The latent function is recovered to well below the noise level on held-out inputs.
    assert (rmse < 0.5 * noise_std).all(), rmse
    learned_noise_std = model.hyperparameters.noise_variance.sqrt()
    assert ((learned_noise_std > noise_std / 1.5) & (learned_noise_std < noise_std * 1.5)).all()
    assert (var > 0).all()


def test_fit_does_not_lower_the_objective():
    x, y = make_data(60, 0.1, seed=2)
    model = DynamicsGP(x, y)
    model.train()
    with torch.no_grad():
        before = model.log_evidence()
    after = model.fit(restarts=2, max_iter=30, generator=torch.Generator().manual_seed(0))
    assert (after >= before - 1e-9).all()


def failing_evidence(model: DynamicsGP, fails: set[int] | None = None, after: int | None = None, nan: bool = False):
    """Make the line search's evaluations (with gradient) numbered in ``fails``, or all past ``after``, fail.

    Returns the count of those evaluations (``"n"``) and the summed objectives of the ones that succeeded.
    """
    calls = {"n": 0, "values": []}
    evidence = model.log_evidence

    def evaluate() -> torch.Tensor:
        if torch.is_grad_enabled():
            calls["n"] += 1
            if calls["n"] in (fails or set()) or (after is not None and calls["n"] > after):
                if nan:
                    return evidence() * math.nan
                raise NotPSDError("a trial θ whose covariance is not positive definite")
            value = evidence()
            calls["values"].append(float(value.sum()))
            return value
        return evidence()

    model.log_evidence = evaluate  # the instance attribute shadows the method
    return calls


@pytest.mark.parametrize("nan", [False, True], ids=["factorisation_error", "nan_objective"])
def test_a_failed_line_search_step_resumes_from_the_best_theta(nan):
    # A trial θ that fails (as a step to ℓ ~ e⁻²¹⁵ did in a mountain-car fit) costs neither the run nor the
    # optimum: the run goes on from the best θ evaluated and ends where an unfailing run ends.
    x, y = make_data(80, 0.1, seed=3)
    reference = DynamicsGP(x, y)
    expected = reference._optimise(100)
    model = DynamicsGP(x, y)
    calls = failing_evidence(model, fails={4, 9}, nan=nan)
    health.take()
    value = model._optimise(100)
    assert calls["n"] > 9
    assert health.take()[health.GP_FIT_FAILED] == 2
    assert torch.isfinite(value).all()
    assert (value - expected).abs().max() < 1e-4, (value, expected)


def test_a_line_search_failing_for_good_ends_at_the_best_theta_evaluated():
    x, y = make_data(80, 0.1, seed=3)
    model = DynamicsGP(x, y)
    model.train()
    with torch.no_grad():
        start = model.log_evidence().sum()
    calls = failing_evidence(model, after=5)
    health.take()
    value = model._optimise(100)
    assert health.take()[health.GP_FIT_FAILED] == FIT_RESUMES + 1
    best = max(calls["values"][:5])
    assert best > float(start)
    assert float(value.sum()) == pytest.approx(best, abs=1e-9)


def test_a_failure_before_any_finite_objective_is_raised():
    x, y = make_data(40, 0.1, seed=3)
    model = DynamicsGP(x, y)
    failing_evidence(model, fails={1})
    with pytest.raises(NotPSDError):
        model._optimise(50)


@pytest.mark.parametrize("include_noise", [False, True])
def test_batched_model_equals_independent_single_output_models(include_noise):
    x, y = make_data(80, 0.1, seed=3)
    theta = random_theta(2, 3, seed=4)
    batched = DynamicsGP(x, y, theta)
    x_test, _ = make_data(30, 0.0, seed=5)
    mean, var = batched.predict(x_test, include_noise=include_noise)
    for e in range(2):
        single_theta = GPHyperparameters(
            theta.lengthscales[e : e + 1], theta.signal_variance[e : e + 1], theta.noise_variance[e : e + 1]
        )
        single = DynamicsGP(x, y[:, e : e + 1], single_theta)
        m_e, v_e = single.predict(x_test, include_noise=include_noise)
        torch.testing.assert_close(mean[:, e : e + 1], m_e, rtol=0, atol=1e-8)
        torch.testing.assert_close(var[:, e : e + 1], v_e, rtol=0, atol=1e-8)


def test_theta_get_set_round_trip_natural_and_log():
    x, y = make_data(20, 0.1, seed=6)
    theta = random_theta(2, 3, seed=7)
    model = DynamicsGP(x, y)
    model.hyperparameters = theta
    got = model.hyperparameters
    for field in ("lengthscales", "signal_variance", "noise_variance"):
        torch.testing.assert_close(getattr(got, field), getattr(theta, field), rtol=1e-12, atol=0)
    torch.testing.assert_close(GPHyperparameters.from_log(theta.log()).natural(), theta.natural())
    torch.testing.assert_close(GPHyperparameters.from_natural(theta.natural()).log(), theta.log())
    assert theta.natural().shape == (2, 5)
    assert theta.names()[-2:] == ["signal_variance", "noise_variance"]
    assert set(theta.as_dict()) == {f"out{j}/{n}" for j in range(2) for n in theta.names()}


def test_setting_theta_changes_predictions():
    x, y = make_data(30, 0.1, seed=8)
    model = DynamicsGP(x, y, random_theta(2, 3, seed=9))
    before, _ = model.predict(x[:5])
    model.hyperparameters = random_theta(2, 3, seed=10)
    after, _ = model.predict(x[:5])
    assert not torch.allclose(before, after)


def test_save_load_gives_identical_predictions(tmp_path):
    x, y = make_data(40, 0.1, seed=11)
    model = DynamicsGP(x, y, random_theta(2, 3, seed=12))
    path = tmp_path / "gp.pt"
    model.save(path)
    loaded = DynamicsGP.load(path)
    x_test, _ = make_data(10, 0.0, seed=13)
    for a, b in zip(model.predict(x_test), loaded.predict(x_test), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    torch.testing.assert_close(loaded.train_x, model.train_x, rtol=0, atol=0)


def direct_posterior(x, y, theta: GPHyperparameters, x_test):
    """Eq. 1-2 by a direct Cholesky solve, one output at a time."""
    means, variances = [], []
    for e in range(theta.num_outputs):
        ls = theta.lengthscales[e]
        def k(a, b, e=e, ls=ls):
            return theta.signal_variance[e] * torch.exp(-0.5 * torch.cdist(a / ls, b / ls) ** 2)
        K = k(x, x) + theta.noise_variance[e] * torch.eye(x.shape[0], dtype=x.dtype)
        L = torch.linalg.cholesky(K)
        ks = k(x_test, x)
        means.append(ks @ torch.cholesky_solve(y[:, e : e + 1], L).squeeze(-1))
        v = torch.linalg.solve_triangular(L, ks.T, upper=False)
        variances.append(theta.signal_variance[e] - (v**2).sum(0))
    return torch.stack(means, -1), torch.stack(variances, -1)


def test_exact_cholesky_at_2000_points():
    gen = torch.Generator().manual_seed(14)
    x = torch.rand(2000, 3, generator=gen, dtype=torch.float64) * 4 - 2
    y = smooth_function(x)[:, :1] + 1e-3 * torch.randn(2000, 1, generator=gen, dtype=torch.float64)
    # Long length-scales and tiny noise make K + σ²I badly conditioned: CG/Lanczos (GPyTorch's
    # default above 800 points) would miss the direct solve by far more than the tolerance.
    theta = GPHyperparameters(
        torch.tensor([[1.5, 2.0, 2.5]], dtype=torch.float64),
        torch.tensor([1.0], dtype=torch.float64),
        torch.tensor([1e-6], dtype=torch.float64),
    )
    model = DynamicsGP(x, y, theta)
    x_test = torch.rand(50, 3, generator=gen, dtype=torch.float64) * 4 - 2
    mean, var = model.predict(x_test)
    ref_mean, ref_var = direct_posterior(x, y, theta, x_test)
    torch.testing.assert_close(mean, ref_mean, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(var, ref_var.clamp_min(var.min()), rtol=1e-4, atol=1e-8)

    # The log evidence is the exact one: quadratic form and log-determinant from Cholesky.
    K = theta.signal_variance * torch.exp(
        -0.5 * torch.cdist(x / theta.lengthscales[0], x / theta.lengthscales[0]) ** 2
    ) + theta.noise_variance * torch.eye(2000, dtype=torch.float64)
    L = torch.linalg.cholesky(K)
    alpha = torch.cholesky_solve(y, L)
    exact = -0.5 * (y * alpha).sum() - torch.log(torch.diagonal(L)).sum() - 1000 * math.log(2 * math.pi)
    model.train()
    with torch.no_grad(), exact_gp_settings():
        output = model.likelihood(model(*model.train_inputs))
        value = output.log_prob(model.train_targets) / 2000
    torch.testing.assert_close(value, (exact / 2000).reshape(1), rtol=1e-8, atol=1e-10)


def test_posterior_cache_matches_predictions():
    x, y = make_data(50, 0.1, seed=15)
    theta = random_theta(2, 3, seed=16)
    model = DynamicsGP(x, y, theta)
    cache = model.posterior_cache()
    x_test, _ = make_data(7, 0.0, seed=17)
    ls = theta.lengthscales[:, None, None, :]  # E x 1 x 1 x D
    k = theta.signal_variance[:, None, None] * torch.exp(
        -0.5 * (((x_test[None, :, None, :] - x[None, None, :, :]) / ls) ** 2).sum(-1)
    )  # E x m x n
    mean = torch.einsum("emn,en->me", k, cache.beta)
    var = theta.signal_variance[None, :] - torch.einsum("emn,enk,emk->me", k, cache.K_inv, k)
    ref_mean, ref_var = model.predict(x_test)
    torch.testing.assert_close(mean, ref_mean, rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(var, ref_var, rtol=1e-6, atol=1e-10)


@pytest.mark.parametrize(("dtype", "num_outputs"), list(itertools.product([torch.float32, torch.float64], [1, 3])))
def test_dtypes_and_output_counts(dtype, num_outputs):
    gen = torch.Generator().manual_seed(18)
    x = torch.rand(40, 2, generator=gen, dtype=dtype)
    y = torch.sin(3 * x[:, :1]).repeat(1, num_outputs) + 0.05 * torch.randn(40, num_outputs, generator=gen, dtype=dtype)
    model = DynamicsGP(x, y, dtype=dtype)
    model.fit(restarts=1, max_iter=20)
    mean, var = model.predict(x[:4])
    assert mean.dtype == dtype and mean.shape == (4, num_outputs) and var.shape == (4, num_outputs)
    assert model.hyperparameters.lengthscales.shape == (num_outputs, 2)


# -- bad input ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("x", "y", "message"),
    [
        (torch.full((10, 2), math.nan), torch.zeros(10, 1), "train_x contains 20 non-finite"),
        (torch.zeros(10, 2), torch.tensor([[math.inf]] * 10), "train_y contains 10 non-finite"),
        (torch.zeros(10, 2), torch.zeros(9, 1), "train_x has 10 rows but train_y has 9"),
        (torch.zeros(10), torch.zeros(10, 1), "train_x must be `n x D`"),
        (torch.zeros(10, 2), torch.zeros(10), "train_y must be `n x E`"),
        (torch.zeros(2, 2), torch.zeros(2, 1), "at least 3 training points"),
    ],
)
def test_bad_training_data_is_named(x, y, message):
    with pytest.raises(ValueError, match=message):
        DynamicsGP(x, y)


def test_bad_hyperparameters_are_named():
    x, y = make_data(10, 0.1, seed=19)
    model = DynamicsGP(x, y)
    with pytest.raises(ValueError, match="E=1 outputs and D=3 inputs, the model has E=2 and D=3"):
        model.hyperparameters = random_theta(1, 3, seed=0)
    with pytest.raises(ValueError, match="noise_variance"):
        model.hyperparameters = GPHyperparameters(
            torch.ones(2, 3, dtype=torch.float64),
            torch.ones(2, dtype=torch.float64),
            torch.full((2,), NOISE_VARIANCE_MIN / 10, dtype=torch.float64),
        )
    with pytest.raises(ValueError, match="lengthscales must be finite and strictly positive"):
        GPHyperparameters(-torch.ones(2, 3), torch.ones(2), torch.ones(2))


def test_a_noise_variance_at_the_floor_after_rounding_is_the_floor():
    """σ_ε² = floor·(1 − 4e-16), as exp(log σ²) of a fit that reached the floor gives: set just above it, no error."""
    x, y = make_data(10, 0.1, seed=19)
    model = DynamicsGP(x, y)
    rounded = torch.tensor([NOISE_VARIANCE_MIN * (1 - 4e-16), 1e-3], dtype=torch.float64)
    model.hyperparameters = GPHyperparameters(torch.ones(2, 3, dtype=torch.float64), torch.ones(2, dtype=torch.float64),
                                              rounded)
    noise = model.hyperparameters.noise_variance
    assert NOISE_VARIANCE_MIN < noise[0] <= NOISE_VARIANCE_MIN * (1 + 2e-6)
    torch.testing.assert_close(noise[1], rounded[1], rtol=1e-12, atol=0)
    # A round trip through the log form, as fit_warm makes, keeps it settable.
    model.hyperparameters = GPHyperparameters.from_log(model.hyperparameters.log())
    with pytest.raises(ValueError, match="signal_variance must have shape"):
        GPHyperparameters(torch.ones(2, 3), torch.ones(3), torch.ones(2))
    with pytest.raises(ValueError, match="x must be `m x 3`"):
        model.predict(torch.zeros(4, 2))
    with pytest.raises(ValueError, match="restarts must be >= 1"):
        model.fit(restarts=0)


def test_missing_and_corrupt_checkpoints_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="no DynamicsGP checkpoint"):
        DynamicsGP.load(tmp_path / "absent.pt")
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="corrupt DynamicsGP checkpoint"):
        DynamicsGP.load(garbage)
    wrong = tmp_path / "wrong.pt"
    torch.save({"format": "something else"}, wrong)
    with pytest.raises(ValueError, match="not a DynamicsGP state"):
        DynamicsGP.load(wrong)


def test_prediction_at_many_points_is_chunked_and_consistent():
    x, y = make_data(30, 0.1, seed=20)
    model = DynamicsGP(x, y, random_theta(2, 3, seed=21))
    x_test, _ = make_data(3000, 0.0, seed=22)  # several chunks; a single call would form 3000²
    mean, var = model.predict(x_test)
    ref_mean, ref_var = direct_posterior(x, y, model.hyperparameters, x_test)
    torch.testing.assert_close(mean, ref_mean, rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(var, ref_var, rtol=1e-6, atol=1e-10)
