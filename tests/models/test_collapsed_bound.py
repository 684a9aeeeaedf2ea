"""The collapsed bound in closed form: its cross-covariance against GPyTorch's kernel, its value against the dense
SGPR density, its backward against finite differences, and the sparse model's evidence against GPyTorch's own."""

from __future__ import annotations

import math
from pathlib import Path

import gpytorch
import numpy as np
import pytest
import torch
from torch import Tensor

from qtl.models import GPHyperparameters, SparseDynamicsGP
from qtl.models.collapsed_bound import collapsed_bound, se_cross_covariance

DTYPE = torch.float64


def problem(n: int, m: int, outputs: int, dim: int, seed: int) -> dict[str, Tensor]:
    """Inputs `n x D`, targets `E x n`, inducing inputs `m x D` near the data, ℓ `E x D`, α² and σ² `E`."""
    gen = torch.Generator().manual_seed(seed)
    x = 3 * torch.rand(n, dim, generator=gen, dtype=DTYPE) + 1  # off the origin: the centring matters
    w = torch.randn(dim, outputs, generator=gen, dtype=DTYPE)
    y = (torch.sin(x @ w) + 0.05 * torch.randn(n, outputs, generator=gen, dtype=DTYPE)).T.contiguous()
    z = x[torch.randperm(n, generator=gen)[:m]] + 0.01 * torch.randn(m, dim, generator=gen, dtype=DTYPE)
    return {"inputs": x, "targets": y, "inducing": z,
            "lengthscales": 0.5 + torch.rand(outputs, dim, generator=gen, dtype=DTYPE),
            "signal_variance": 0.5 + torch.rand(outputs, generator=gen, dtype=DTYPE),
            "noise_variance": 0.01 + 0.05 * torch.rand(outputs, generator=gen, dtype=DTYPE)}


def dense_bound(p: dict[str, Tensor], jitter: float) -> Tensor:
    """Titsias' bound by the dense `n x n` density of N(0, Q + σ²I) and the trace term, per output `E`."""
    kernel = gpytorch.kernels.RBFKernel(ard_num_dims=p["inputs"].shape[1], batch_shape=p["lengthscales"].shape[:1])
    kernel.to(DTYPE)
    lengthscale = p["lengthscales"][:, None, :]

    def k(a: Tensor, b: Tensor) -> Tensor:
        diff = (a[None, :, None, :] - b[None, None, :, :]) / lengthscale[:, None]  # E x |a| x |b| x D
        return p["signal_variance"][:, None, None] * torch.exp(-0.5 * diff.square().sum(-1))

    x, z, n = p["inputs"], p["inducing"], p["inputs"].shape[0]
    k_uu = k(z, z) + (jitter * p["signal_variance"])[:, None, None] * torch.eye(z.shape[0], dtype=DTYPE)
    k_fu = k(x, z)
    q = k_fu @ torch.linalg.solve(k_uu, k_fu.mT)
    noise = p["noise_variance"][:, None, None] * torch.eye(n, dtype=DTYPE)
    fit = torch.distributions.MultivariateNormal(torch.zeros_like(p["targets"]), covariance_matrix=q + noise)
    trace = n * p["signal_variance"] - q.diagonal(dim1=-2, dim2=-1).sum(-1)
    return fit.log_prob(p["targets"]) - 0.5 * trace / p["noise_variance"]


def test_the_cross_covariance_is_gpytorchs_se_kernel():
    p = problem(30, 7, 3, 4, seed=0)
    kernel = gpytorch.kernels.ScaleKernel(gpytorch.kernels.RBFKernel(ard_num_dims=4, batch_shape=torch.Size([3])),
                                          batch_shape=torch.Size([3])).to(DTYPE)
    kernel.base_kernel.lengthscale = p["lengthscales"][:, None, :]
    kernel.outputscale = p["signal_variance"]
    with torch.no_grad():
        want = kernel(p["inputs"].expand(3, -1, -1), p["inducing"].expand(3, -1, -1)).to_dense()
    got = se_cross_covariance(p["inputs"], p["inducing"], p["lengthscales"], p["signal_variance"])
    torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("jitter", [0.0, 1e-6, 1e-2])
def test_the_bound_equals_the_dense_density_minus_the_trace_term(jitter):
    p = problem(40, 9, 3, 4, seed=1)
    leaves = {name: p[name].clone().requires_grad_() for name in ("inducing", "lengthscales", "signal_variance",
                                                                    "noise_variance")}
    got = collapsed_bound(p["inputs"], p["targets"], jitter=jitter, **leaves)
    want = dense_bound({**p, **leaves}, jitter)
    torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-9)
    got_grads = torch.autograd.grad(got.sum(), list(leaves.values()))
    want_grads = torch.autograd.grad(want.sum(), list(leaves.values()))
    for name, g, w in zip(leaves, got_grads, want_grads, strict=True):
        torch.testing.assert_close(g, w, rtol=1e-7, atol=1e-9, msg=lambda text, name=name: f"∂F/∂{name}: {text}")


def test_the_whole_bound_against_finite_differences():
    p = problem(13, 4, 2, 3, seed=4)
    leaves = tuple(p[name].requires_grad_() for name in ("inducing", "lengthscales", "signal_variance",
                                                          "noise_variance"))

    def bound(z: Tensor, ls: Tensor, sv: Tensor, nv: Tensor) -> Tensor:
        return collapsed_bound(p["inputs"], p["targets"], z, ls, sv, nv, jitter=1e-3)

    assert torch.autograd.gradcheck(bound, leaves, eps=1e-6, atol=1e-7, rtol=1e-6)


def crowded_model(n: int, m: int, seed: int) -> SparseDynamicsGP:
    """A sparse model whose m inducing inputs crowd the data at its lengthscales (K_uu near singular), δ = 1e-6 α²."""
    p = problem(n, m, 4, 6, seed)
    theta = GPHyperparameters(lengthscales=2 + p["lengthscales"], signal_variance=p["signal_variance"],
                              noise_variance=1e-4 * p["noise_variance"])
    return SparseDynamicsGP(p["inputs"], p["targets"].T, theta, inducing_points=p["inducing"], jitter=1e-6)


def assert_evidence_equals_gpytorchs(model: SparseDynamicsGP, value_tol: float) -> None:
    """Evidence equal to GPyTorch's to ``value_tol``, its gradient in every trained parameter to 1e-5 relative."""
    model.train()
    params = [param for param in model.parameters() if param.requires_grad]
    got = model.log_evidence()
    got_grads = torch.autograd.grad(got.sum(), params)
    want = model.gpytorch_log_evidence()
    want_grads = torch.autograd.grad(want.sum(), params)
    torch.testing.assert_close(got, want, rtol=value_tol, atol=value_tol)
    for g, w in zip(got_grads, want_grads, strict=True):
        assert float((g - w).abs().max() / w.abs().max()) < 1e-5


@pytest.mark.parametrize(("n", "m"), [(60, 20), (300, 120)])
def test_the_sparse_models_evidence_equals_gpytorchs(n, m):
    # Value and gradient of every trained parameter (raw θ, Z), priors included, against GPyTorch's marginal
    # likelihood of the same model. K_uu is near singular here (as with learned Z), so the two evaluations of
    # the gradient differ at the level that conditioning sets for any two correct ones (1e-6 relative measured).
    model = crowded_model(n, m, seed=5)
    assert len([param for param in model.parameters() if param.requires_grad]) == 4  # raw noise, Z, raw α², raw ℓ
    assert_evidence_equals_gpytorchs(model, value_tol=1e-10)


REAL_FIT = Path(__file__).parent / "data" / "cartpole_sparse_fit.npz"  # float64 arrays, "source" says whence


def test_on_a_learned_cartpole_model_the_gradient_equals_gpytorchs():
    # A learned model as the sweep meets it (see "source" in the file): Z crowd the data, σ² ~ 5e-6 α², so B has
    # eigenvalues ~1e8 and the gradient is a small difference of large terms. β = B⁻¹ r by the explicit inverse
    # instead of solves gives 1e-3 relative error here (the whole model, n = 1250 and m = 300: 0.7 against 2e-6).
    with np.load(REAL_FIT) as arrays:
        data = {key: torch.from_numpy(arrays[key]) for key in arrays.files if key not in ("jitter", "source")}
        data["jitter"] = float(arrays["jitter"])
    theta = GPHyperparameters(lengthscales=data["lengthscales"], signal_variance=data["signal_variance"],
                              noise_variance=data["noise_variance"])
    model = SparseDynamicsGP(data["inputs"], data["targets"], theta, inducing_points=data["inducing"],
                             jitter=data["jitter"])
    assert_evidence_equals_gpytorchs(model, value_tol=1e-9)


def test_a_fit_through_the_closed_form_reaches_gpytorchs_optimum():
    # One L-BFGS run each from the same θ and Z: the same objective and nearly the same θ.
    results = []
    for evidence in ("closed_form", "gpytorch"):
        model = crowded_model(120, 30, seed=6)
        model.hyperparameters = model.heuristic_hyperparameters()
        if evidence == "gpytorch":
            model.log_evidence = model.gpytorch_log_evidence  # the instance attribute shadows the method
        value = model._optimise(60)
        results.append((value, model.hyperparameters.log()))
    (value, log_theta), (ref_value, ref_log_theta) = results
    assert math.isfinite(float(value.sum()))
    torch.testing.assert_close(value, ref_value, rtol=0, atol=1e-5)
    torch.testing.assert_close(log_theta, ref_log_theta, rtol=0, atol=1e-2)
