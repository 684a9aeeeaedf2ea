"""Gaussian state type: shapes, batching, sampling, and joint-Gaussian chaining."""

from __future__ import annotations

import pytest
import torch

from qtl.gaussian import Gaussian, MomentMatch, compose

DTYPE = torch.float64


def test_shapes_and_batch_broadcast():
    g = Gaussian(torch.zeros(3, 2, dtype=DTYPE), torch.eye(2, dtype=DTYPE))
    assert g.dim == 2 and g.batch_shape == (3,) and g.dtype == DTYPE
    item = g[1]
    assert item.mean.shape == (2,) and item.cov.shape == (2, 2)
    stacked = Gaussian.stack([g, g], dim=0)
    assert stacked.mean.shape == (2, 3, 2) and stacked.cov.shape == (2, 3, 2, 2)


@pytest.mark.parametrize(("mean_shape", "cov_shape"), [((2,), (3, 3)), ((), ()), ((4, 2), (3, 2, 2))])
def test_rejects_bad_shapes(mean_shape, cov_shape):
    with pytest.raises((ValueError, RuntimeError)):
        Gaussian(torch.zeros(mean_shape), torch.zeros(cov_shape))


def test_sample_moments_with_singular_cov(mc):
    # A rank-1 covariance: sampling must not need a Cholesky factor.
    direction = torch.tensor([1.0, 2.0, -1.0], dtype=DTYPE)
    cov = torch.outer(direction, direction) * 0.3
    mean = torch.tensor([0.5, -1.0, 2.0], dtype=DTYPE)
    x = Gaussian(mean, cov).sample(100_000, generator=torch.Generator().manual_seed(0))
    assert x.shape == (100_000, 3)
    mc.assert_mean(mean, x, "sample mean")
    centred = x - x.mean(0)
    mc.assert_mean(cov, centred[:, :, None] * centred[:, None, :], "sample cov")


def test_compose_of_linear_maps_is_exact():
    gen = torch.Generator().manual_seed(1)
    cov = torch.randn(3, 3, generator=gen, dtype=DTYPE)
    cov = cov @ cov.T + torch.eye(3, dtype=DTYPE)
    a = torch.randn(2, 3, generator=gen, dtype=DTYPE)
    b = torch.randn(4, 2, generator=gen, dtype=DTYPE)
    first = MomentMatch(mean=torch.zeros(2), cov=a @ cov @ a.T, cross_cov=cov @ a.T, gain=a.T)
    second = MomentMatch(mean=torch.zeros(4), cov=b @ first.cov @ b.T, cross_cov=first.cov @ b.T, gain=b.T)
    both = compose(first, second)
    torch.testing.assert_close(both.cross_cov, cov @ (b @ a).T)
    torch.testing.assert_close(both.gain, (b @ a).T)
