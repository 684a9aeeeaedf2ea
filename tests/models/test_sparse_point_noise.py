"""Per-point noise σ_ε² + c_i in the sparse GP (SGPR with Λ = σ_ε²I + C): the collapsed bound against the dense formula,
GPyTorch and the exact GP, its closed-form backward, the posterior cache, the pathwise root, checkpoints."""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from qtl.models import DynamicsGP, GPHyperparameters, SparseDynamicsGP
from qtl.models.collapsed_bound import collapsed_bound

DTYPE = torch.float64

THETA = GPHyperparameters(lengthscales=torch.tensor([[1.0, 1.5, 0.8], [0.9, 1.1, 1.3]], dtype=DTYPE),
                          signal_variance=torch.tensor([0.7, 1.2], dtype=DTYPE),
                          noise_variance=torch.tensor([0.01, 0.02], dtype=DTYPE))


def data(n: int = 24, seed: int = 0) -> tuple[Tensor, Tensor]:
    """Inputs `n x 3` and two smooth noisy targets `n x 2`."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 3, generator=gen, dtype=DTYPE) + 1  # off the origin: the bound's centring matters
    y = torch.stack([x[:, 0].sin(), x[:, 1] * x[:, 2]], dim=-1)
    return x, y + 0.05 * torch.randn(n, 2, generator=gen, dtype=DTYPE)


def extras(n: int, seed: int = 1) -> Tensor:
    """Extra noise c >= 0 `n x 2` up to 20 σ_ε² (relevance down to 1/21), a third of it 0 (the target's own)."""
    gen = torch.Generator().manual_seed(seed)
    c = 20 * torch.rand(n, 2, generator=gen, dtype=DTYPE) * THETA.noise_variance
    c[::3] = 0.0
    return c


def se(a: Tensor, b: Tensor, lengthscales: Tensor, alpha2: float) -> Tensor:
    """The SE kernel of Eq. 3 by hand: `len(a) x len(b)`."""
    diff = (a[:, None, :] - b[None, :, :]) / lengthscales
    return alpha2 * torch.exp(-0.5 * diff.square().sum(-1))


def dense_bound(x: Tensor, y: Tensor, z: Tensor, theta: GPHyperparameters, c: Tensor, jitter: float) -> Tensor:
    """log N(y | 0, Q_nn + Λ) − ½ tr(Λ⁻¹ (K_nn − Q_nn)), Λ = σ²I + C, by dense `n x n` algebra: `E`."""
    values = []
    for e in range(y.shape[1]):
        ls, a2, sn2 = theta.lengthscales[e], float(theta.signal_variance[e]), float(theta.noise_variance[e])
        k_uu = se(z, z, ls, a2) + jitter * a2 * torch.eye(len(z), dtype=DTYPE)
        k_fu = se(x, z, ls, a2)
        q = k_fu @ torch.linalg.solve(k_uu, k_fu.T)
        noise = sn2 + c[:, e]
        fit = torch.distributions.MultivariateNormal(torch.zeros(len(x), dtype=DTYPE), q + torch.diag(noise))
        values.append(fit.log_prob(y[:, e]) - 0.5 * ((a2 - q.diagonal()) / noise).sum())
    return torch.stack(values)


def dense_sigma(model: SparseDynamicsGP, c: Tensor, e: int) -> tuple[Tensor, Tensor, Tensor]:
    """K_mm + δI, K_mn and Σ = K_mm + δI + K_mn Λ⁻¹ K_nm of output e, by hand."""
    theta, z, x = model.hyperparameters, model.inducing_points, model.train_x
    ls, a2, sn2 = theta.lengthscales[e], float(theta.signal_variance[e]), float(theta.noise_variance[e])
    k_mm = se(z, z, ls, a2) + model.jitter * a2 * torch.eye(len(z), dtype=DTYPE)
    k_mn = se(z, x, ls, a2)
    return k_mm, k_mn, k_mm + k_mn @ torch.diag(1 / (sn2 + c[:, e])) @ k_mn.T


@pytest.mark.parametrize("jitter", [0.0, 1e-3])
def test_the_bound_with_per_point_noise_equals_the_dense_formula(jitter):
    x, y = data(30)
    c = extras(30)
    z = x[::3] + 0.05
    got = collapsed_bound(x, y.T.contiguous(), z, THETA.lengthscales, THETA.signal_variance, THETA.noise_variance,
                          jitter, c.T.contiguous())
    torch.testing.assert_close(got, dense_bound(x, y, z, THETA, c, jitter), rtol=1e-10, atol=1e-9)


def test_the_models_bound_equals_gpytorchs_in_value_and_gradient():
    # GPyTorch's marginal likelihood reads the per-point noise from the likelihood (its Gaussian density and the
    # inducing-point trace term alike): the same bound, priors included, and the gradient of every trained parameter.
    x, y = data(40)
    model = SparseDynamicsGP(x, y, THETA, num_inducing=12, generator=torch.Generator().manual_seed(3), jitter=1e-4,
                             extra_noise=extras(40))
    model.train()
    params = [param for param in model.parameters() if param.requires_grad]
    assert len(params) == 4  # raw noise, Z, raw α², raw ℓ
    got = model.log_evidence()
    got_grads = torch.autograd.grad(got.sum(), params)
    want = model.gpytorch_log_evidence()
    want_grads = torch.autograd.grad(want.sum(), params)
    model.eval()
    torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)
    for g, w in zip(got_grads, want_grads, strict=True):
        torch.testing.assert_close(g, w, rtol=1e-7, atol=1e-9)


def test_the_closed_form_backward_with_per_point_noise_passes_gradcheck():
    x, y = data(14)
    c = extras(14).T.contiguous()
    z = (x[::3] + 0.1).requires_grad_()
    ls = THETA.lengthscales.clone().requires_grad_()
    sv = THETA.signal_variance.clone().requires_grad_()
    nv = THETA.noise_variance.clone().requires_grad_()
    targets = y.T.contiguous()
    for jitter in (0.0, 1e-3):
        assert torch.autograd.gradcheck(
            lambda ls, sv, nv, z, jitter=jitter: collapsed_bound(x, targets, z, ls, sv, nv, jitter, c),
            (ls, sv, nv, z), eps=1e-6, atol=1e-6, rtol=1e-5)


@pytest.fixture(scope="module")
def twins() -> tuple[DynamicsGP, SparseDynamicsGP, Tensor]:
    """The exact GP with per-point noise and its sparse twin at Z = X without jitter, and the extra noise `n x 2`."""
    x, y = data(20)
    c = extras(20)
    exact = DynamicsGP(x, y, THETA, extra_noise=c)
    sparse = SparseDynamicsGP(x, y, THETA, inducing_points=x, jitter=0.0, extra_noise=c)
    return exact, sparse, c


def test_at_z_equal_x_the_bound_is_the_exact_evidence(twins):
    exact, sparse, _ = twins
    exact.train(), sparse.train()
    with torch.no_grad():  # Q_nn = K_nn: the trace term vanishes
        got, want = sparse.log_evidence(), exact.log_evidence()
    exact.eval(), sparse.eval()
    torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-10)


def test_at_z_equal_x_the_cache_predicts_as_the_exact_gp(twins):
    exact, sparse, c = twins
    test = torch.randn(9, 3, generator=torch.Generator().manual_seed(5), dtype=DTYPE) + 1
    for noise in (False, True):
        for got, want in zip(sparse.predict(test, include_noise=noise), exact.predict(test, include_noise=noise),
                             strict=True):
            torch.testing.assert_close(got, want, rtol=1e-8, atol=1e-10)
    cache = sparse.posterior_cache()
    torch.testing.assert_close(cache.extra_noise, c.T, rtol=0, atol=0)
    exact_cache = exact.posterior_cache()  # at Z = X: the same β and K⁻¹ − Σ⁻¹ = (K + Λ)⁻¹
    torch.testing.assert_close(cache.beta, exact_cache.beta, rtol=1e-8, atol=1e-8)
    torch.testing.assert_close(cache.K_inv, exact_cache.K_inv, rtol=1e-7, atol=1e-7)


def test_the_exact_twin_carries_the_extra_noise(twins):
    exact, sparse, c = twins
    twin = sparse.exact()
    torch.testing.assert_close(twin.extra_noise, c.T, rtol=0, atol=0)
    test = torch.randn(5, 3, generator=torch.Generator().manual_seed(6), dtype=DTYPE)
    torch.testing.assert_close(twin.predict(test)[1], exact.predict(test)[1], rtol=0, atol=0)


@pytest.mark.parametrize("jitter", [0.0, 1e-3])
def test_the_cache_and_the_pathwise_root_are_the_heteroscedastic_formulas(jitter):
    # m < n: β = Σ⁻¹ K_mn Λ⁻¹ y, K_inv = K_mm⁻¹ − Σ⁻¹, and R Rᵀ = Σ⁻¹ + δ K_mm⁻² (K_mm with its jitter δI).
    x, y = data(30)
    c = extras(30)
    model = SparseDynamicsGP(x, y, THETA, num_inducing=10, generator=torch.Generator().manual_seed(1), jitter=jitter,
                             extra_noise=c)
    cache = model.posterior_cache()
    for e in range(2):
        k_mm, k_mn, sigma = dense_sigma(model, c, e)
        noise = float(THETA.noise_variance[e]) + c[:, e]
        sigma_inv, k_mm_inv = torch.linalg.inv(sigma), torch.linalg.inv(k_mm)
        torch.testing.assert_close(cache.beta[e], sigma_inv @ k_mn @ (y[:, e] / noise), rtol=1e-8, atol=1e-9)
        torch.testing.assert_close(cache.K_inv[e], k_mm_inv - sigma_inv, rtol=1e-7, atol=1e-8)
        delta = jitter * float(THETA.signal_variance[e])
        root = cache.update_root[e]
        torch.testing.assert_close(root @ root.T, sigma_inv + delta * k_mm_inv @ k_mm_inv, rtol=1e-7, atol=1e-9)


def test_zero_extra_noise_equals_the_homoscedastic_model():
    x, y = data(30)
    kwargs = {"num_inducing": 10, "generator": torch.Generator().manual_seed(2), "jitter": 1e-4}
    plain = SparseDynamicsGP(x, y, THETA, **kwargs)
    kwargs["generator"] = torch.Generator().manual_seed(2)
    unit = SparseDynamicsGP(x, y, THETA, extra_noise=torch.zeros(30, dtype=DTYPE), **kwargs)
    torch.testing.assert_close(unit.inducing_points, plain.inducing_points, rtol=0, atol=0)
    values, grads = [], []
    for model in (plain, unit):
        model.train()
        value = model.log_evidence()
        values.append(value.detach())
        grads.append(torch.autograd.grad(value.sum(), [p for p in model.parameters() if p.requires_grad]))
        model.eval()
    torch.testing.assert_close(values[1], values[0], rtol=1e-14, atol=1e-14)
    for got, want in zip(grads[1], grads[0], strict=True):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-13)
    a, b = plain.posterior_cache(), unit.posterior_cache()
    assert a.extra_noise is None
    for name in ("beta", "K_inv", "update_root"):
        torch.testing.assert_close(getattr(b, name), getattr(a, name), rtol=1e-12, atol=1e-12)


def test_vanishing_relevance_leaves_the_target_data_alone():
    # Source tuples of extra noise 1e10 σ_ε² (w ~ 1e-10) and offset targets: the sparse model of the target's own
    # tuples at the same Z, in the prediction and in the bound (but for the source tuples' log-normalisers).
    x, y = data(30)
    own = 18
    c = torch.zeros(30, 2, dtype=DTYPE)
    c[own:] = 1e10 * THETA.noise_variance
    shifted = y + torch.cat([torch.zeros(own, 2), torch.full((30 - own, 2), 3.0)]).to(DTYPE)
    z = x[:own:2]
    target = SparseDynamicsGP(x[:own], y[:own], THETA, inducing_points=z, jitter=1e-6)
    weighted = SparseDynamicsGP(x, shifted, THETA, inducing_points=z, jitter=1e-6, extra_noise=c)
    test = torch.randn(9, 3, generator=torch.Generator().manual_seed(2), dtype=DTYPE) + 1
    for got, want in zip(weighted.predict(test), target.predict(test), strict=True):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-8)
    bounds = [collapsed_bound(m.train_x, m.train_targets, z, THETA.lengthscales, THETA.signal_variance,
                              THETA.noise_variance, 1e-6, m.extra_noise) for m in (target, weighted)]
    source_terms = -0.5 * ((30 - own) * math.log(2 * math.pi) + (THETA.noise_variance + c[own:]).log().sum(0))
    torch.testing.assert_close(bounds[1], bounds[0] + source_terms, rtol=1e-12, atol=1e-6)


def test_a_checkpoint_round_trip_keeps_the_extra_noise(tmp_path):
    x, y = data()
    model = SparseDynamicsGP(x, y, THETA, num_inducing=8, extra_noise=extras(len(x)))
    model.save(tmp_path / "gp.pt")
    loaded = SparseDynamicsGP.load(tmp_path / "gp.pt")
    assert isinstance(loaded, SparseDynamicsGP)
    torch.testing.assert_close(loaded.extra_noise, model.extra_noise, rtol=0, atol=0)
    assert "extra_noise" not in SparseDynamicsGP(x, y, THETA, num_inducing=8).state()


def test_fitting_keeps_the_extra_noise_cold_and_warm():
    x, y = data(30)
    c = extras(30)
    model = SparseDynamicsGP(x, y, num_inducing=8, generator=torch.Generator().manual_seed(0), extra_noise=c)
    value = model.fit(restarts=2, max_iter=15, generator=torch.Generator().manual_seed(1))
    assert math.isfinite(float(value.sum()))
    torch.testing.assert_close(model.extra_noise, c.T, rtol=0, atol=0)
    warm = SparseDynamicsGP(x, y, num_inducing=8, generator=torch.Generator().manual_seed(0), extra_noise=c)
    value = warm.fit_warm(model.hyperparameters, model.fit_objective, inducing=model.inducing_points, max_iter=10)
    assert math.isfinite(float(value.sum()))
    torch.testing.assert_close(warm.extra_noise, c.T, rtol=0, atol=0)
