"""Shared fixtures: small GP dynamics models and Monte Carlo checks of moment matching."""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence

import pytest
import torch
from torch import Tensor

from qtl.features import AngleFeatures
from qtl.gaussian import MomentMatch
from qtl.models import DynamicsGP, GPHyperparameters, GPPosteriorCache

# Under pytest-xdist (`pytest -n 2`, the README's command) each worker gets one torch thread, and the
# subprocesses it starts inherit OMP_NUM_THREADS=1: two workers then share the two cores instead of
# four threads fighting for them. A test that wants threads sets them itself.
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ["OMP_NUM_THREADS"] = "1"
    torch.set_num_threads(1)

DTYPE = torch.float64
# Monte Carlo acceptance rule: an analytic moment passes when it lies within MC_Z standard
# errors of the sample estimate, the standard error estimated from the per-sample terms
# themselves (std / √N). At 5 SE one entry fails by chance with probability ~6e-7, and the
# seeds are fixed anyway. MC_ATOL covers entries whose samples have (numerically) zero spread.
MC_Z = 5.0
MC_ATOL = 1e-10
MC_SAMPLES = 100_000


class MonteCarlo:
    """Monte Carlo references for the moments of f(x), x Gaussian, with SE-derived tolerances."""

    z = MC_Z  # standard errors an estimate may be off by

    @staticmethod
    def assert_mean(analytic: Tensor, per_sample: Tensor, what: str = "") -> None:
        """|analytic − mean(Z)| <= MC_Z · std(Z)/√N + MC_ATOL for each entry; Z is `N x ...`."""
        estimate = per_sample.mean(0)
        std_err = per_sample.std(0) / math.sqrt(per_sample.shape[0])
        excess = (analytic - estimate).abs() - (MC_Z * std_err + MC_ATOL)
        worst = ((analytic - estimate).abs() / (std_err + MC_ATOL)).max().item()
        assert (excess <= 0).all(), f"{what}: analytic {analytic} vs MC {estimate} (worst {worst:.1f} SE, limit {MC_Z})"

    @classmethod
    def assert_moments(
        cls,
        result: MomentMatch,
        x: Tensor,
        f: Tensor,
        conditional_var: Tensor | None = None,
    ) -> None:
        """Check mean, covariance and cross-covariance of f(x) from samples x `N x D`, f `N x F`.

        ``conditional_var`` `N x F`: variance of independent noise given x (the GP's posterior
        variance), added to the covariance per the law of total variance.
        """
        cls.assert_mean(result.mean, f, "mean")
        f_c, x_c = f - f.mean(0), x - x.mean(0)
        cov_terms = f_c[:, :, None] * f_c[:, None, :]
        if conditional_var is not None:
            cov_terms = cov_terms + torch.diag_embed(conditional_var)
        cls.assert_mean(result.cov, cov_terms, "cov")
        cls.assert_mean(result.cross_cov, x_c[:, :, None] * f_c[:, None, :], "cross_cov")


@pytest.fixture(scope="session")
def mc() -> type[MonteCarlo]:
    """The Monte Carlo checks."""
    return MonteCarlo


def gp_posterior(cache: GPPosteriorCache, x: Tensor) -> tuple[Tensor, Tensor]:
    """Latent GP posterior mean and variance `m x E` at deterministic inputs `m x D` (Eq. 1-2)."""
    theta = cache.hyperparameters
    xs = x / theta.lengthscales[:, None, :]  # E x m x D
    data = cache.inputs / theta.lengthscales[:, None, :]  # E x n x D
    sq_dist = (xs.square().sum(-1)[..., None] + data.square().sum(-1)[..., None, :] - 2 * xs @ data.mT).clamp_min(0.0)
    kern = theta.signal_variance[:, None, None] * torch.exp(-0.5 * sq_dist)  # E x m x n
    mean = (kern * cache.beta[:, None, :]).sum(-1)
    var = theta.signal_variance[:, None] - ((kern @ cache.K_inv) * kern).sum(-1)
    return mean.T, var.T


@pytest.fixture(scope="session")
def posterior() -> Callable[[GPPosteriorCache, Tensor], tuple[Tensor, Tensor]]:
    """:func:`gp_posterior`, checked against ``DynamicsGP.predict`` in the GP tests."""
    return gp_posterior


def _toy_dynamics(x: Tensor, u: Tensor, angle_dims: Sequence[int]) -> Tensor:
    """A smooth, coupled Δ(x, u) `n x D` for synthetic training data."""
    feats = AngleFeatures(x.shape[-1], angle_dims)(x)
    mix = torch.linspace(-1.0, 1.0, feats.shape[-1], dtype=x.dtype)
    drive = feats @ mix + u.sum(-1)
    deltas = [0.3 * torch.sin(drive + i) + 0.1 * feats[:, i % feats.shape[-1]] for i in range(x.shape[-1])]
    return torch.stack(deltas, dim=-1)


def make_gp(
    n: int,
    state_dim: int,
    action_dim: int,
    angle_dims: Sequence[int] = (),
    *,
    seed: int = 0,
    lengthscale: float = 1.5,
) -> DynamicsGP:
    """A GP on Δ of toy dynamics, inputs [φ(x), u], with set θ (no fitting)."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(n, state_dim, generator=gen, dtype=DTYPE)
    u = torch.randn(n, action_dim, generator=gen, dtype=DTYPE)
    y = _toy_dynamics(x, u, angle_dims) + 0.01 * torch.randn(n, state_dim, generator=gen, dtype=DTYPE)
    inputs = torch.cat([AngleFeatures(state_dim, angle_dims)(x), u], dim=-1)
    num_in = inputs.shape[-1]
    ls = lengthscale * (1.0 + 0.3 * torch.rand(state_dim, num_in, generator=gen, dtype=DTYPE))
    theta = GPHyperparameters(
        lengthscales=ls,
        signal_variance=0.1 + y.var(0),
        noise_variance=torch.full((state_dim,), 1e-3, dtype=DTYPE),
    )
    return DynamicsGP(inputs, y, theta)


@pytest.fixture(scope="session")
def gp_factory() -> Callable[..., DynamicsGP]:
    """:func:`make_gp`."""
    return make_gp


def random_cov(dim: int, scale: float, generator: torch.Generator, batch: Sequence[int] = ()) -> Tensor:
    """A random SPD covariance `... x dim x dim` with typical variance ``scale``²."""
    root = torch.randn(*batch, dim, dim, generator=generator, dtype=DTYPE) * scale / math.sqrt(dim)
    return root @ root.mT + 1e-3 * scale**2 * torch.eye(dim, dtype=DTYPE)


@pytest.fixture(scope="session")
def cov_factory() -> Callable[..., Tensor]:
    """:func:`random_cov`."""
    return random_cov


def assert_psd(cov: Tensor, rel_tol: float = 1e-9) -> None:
    """Symmetric to round-off and no eigenvalue below −rel_tol · max(1, largest |eigenvalue|)."""
    assert torch.allclose(cov, cov.mT, atol=1e-12, rtol=0), "covariance not symmetric"
    eig = torch.linalg.eigvalsh(cov)
    floor = -rel_tol * eig.abs().amax(-1, keepdim=True).clamp_min(1.0)
    assert (eig >= floor).all(), f"covariance not PSD: eigenvalues {eig}"


@pytest.fixture(scope="session")
def psd() -> Callable[..., None]:
    """:func:`assert_psd`."""
    return assert_psd
