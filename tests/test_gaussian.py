"""Gaussian state type: shapes, batching, sampling, matrix roots, sample moments, and joint-Gaussian chaining."""

from __future__ import annotations

import pytest
import torch

from qtl.gaussian import Gaussian, MomentMatch, compose, matrix_root, sample_moments, symmetric_root

DTYPE = torch.float64


def test_shapes_and_batch_broadcast():
    g = Gaussian(torch.zeros(3, 2, dtype=DTYPE), torch.eye(2, dtype=DTYPE))
    assert g.dim == 2 and g.batch_shape == (3,) and g.dtype == DTYPE
    item = g[1]
    assert item.mean.shape == (2,) and item.cov.shape == (2, 2)


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


def test_matrix_root_is_cholesky_or_the_symmetric_root_of_a_singular_cov():
    gen = torch.Generator().manual_seed(2)
    root = torch.randn(2, 3, 3, generator=gen, dtype=DTYPE)
    full = root @ root.mT + 0.1 * torch.eye(3, dtype=DTYPE)  # `2 x 3 x 3`, positive definite
    torch.testing.assert_close(matrix_root(full), torch.linalg.cholesky(full), rtol=0, atol=0)
    singular = full.clone()
    singular[1] = torch.diag(torch.tensor([0.5, 0.0, 2.0], dtype=DTYPE))  # one item singular: all take eigh
    roots = matrix_root(singular)
    torch.testing.assert_close(roots @ roots.mT, singular)
    torch.testing.assert_close(roots, symmetric_root(singular), rtol=0, atol=0)
    assert not torch.allclose(roots[0], torch.linalg.cholesky(full[0]))  # not triangular: the symmetric root


@pytest.mark.parametrize("dim", [-2, -3, 0])
def test_sample_moments_are_the_sample_mean_and_unbiased_covariance(dim):
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(6, 4, 2, 3, generator=gen, dtype=DTYPE)  # the sample dimension is `dim`
    fitted = sample_moments(x, dim=dim)
    moved = x.movedim(dim, 0)  # P x ... x D
    assert fitted.mean.shape == moved.shape[1:] and fitted.cov.shape == (*moved.shape[1:], 3)
    torch.testing.assert_close(fitted.mean, moved.mean(0))
    flat = moved.flatten(1, -2)  # P x B x D
    for item in range(flat.shape[1]):
        torch.testing.assert_close(fitted.cov.flatten(0, -3)[item], torch.cov(flat[:, item].T))


def test_sample_moments_reject_the_event_dimension():
    with pytest.raises(ValueError, match="sample dimension"):
        sample_moments(torch.zeros(5, 3), dim=-1)
