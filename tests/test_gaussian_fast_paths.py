"""The fast paths of qtl.gaussian and of the linear step's moment terms against the general ones they skip."""

from __future__ import annotations

import pytest
import torch

from qtl.gaussian import batch_matmul, batch_shapes
from qtl.propagation.integration import LinearIntegration, SpeedIntegration
from qtl.task import Kinematics

DTYPE = torch.float64


@pytest.mark.parametrize(
    "shapes",
    [(), ((),), ((2,), (2,)), ((), (3,)), ((2, 3), (3,)), ((2, 1), (3,)), ((1,), (4,)), ((4, 1, 2), (3, 1)),
     ((2,), (2,), ())],
)
def test_batch_shapes_is_broadcast_shapes(shapes):
    assert batch_shapes(*map(torch.Size, shapes)) == torch.broadcast_shapes(*shapes)


def test_batch_shapes_raises_as_broadcast_shapes():
    with pytest.raises(RuntimeError):
        batch_shapes(torch.Size([2]), torch.Size([3]))


@pytest.mark.parametrize("batch", [(), (3,), (2, 3)])
def test_batch_matmul_is_matmul(batch):
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(*batch, 4, 5, generator=gen, dtype=DTYPE)
    b = torch.randn(*batch, 5, 2, generator=gen, dtype=DTYPE)
    torch.testing.assert_close(batch_matmul(a, b), a @ b, rtol=1e-15, atol=1e-15)


def _joint(batch: tuple[int, ...], dim: int, modelled: int, seed: int) -> tuple[torch.Tensor, ...]:
    """μ, Σ, μ_Δ, Σ_Δ, C of a random joint Gaussian of (x_t, Δ) with batch ``batch``."""
    gen = torch.Generator().manual_seed(seed)
    size = dim + modelled
    root = torch.randn(*batch, size, size, generator=gen, dtype=DTYPE)
    cov = root @ root.mT
    cov = 0.5 * (cov + cov.mT)
    mean = torch.randn(*batch, size, generator=gen, dtype=DTYPE)
    return mean[..., :dim], cov[..., :dim, :dim], mean[..., dim:], cov[..., dim:, dim:], cov[..., :dim, dim:]


def test_one_batch_dimension_moment_terms_equal_the_general_form():
    # The bmm form (one batch dimension) against the general matmul form (the same joint with a second batch
    # dimension of size 1): equal to round-off, and both covariance summands exactly symmetric.
    integration = SpeedIntegration(5, Kinematics((0, 3), (4, 1), 0.7))
    joint = _joint((3,), 5, 3, seed=2)
    fast = integration.moment_terms(*joint)
    general = integration.moment_terms(*(t[:, None] for t in joint))
    for got, want in zip(fast, general, strict=True):
        torch.testing.assert_close(got, want.squeeze(1), rtol=1e-14, atol=1e-14)
    assert torch.equal(fast[1], fast[1].mT) and torch.equal(fast[3], fast[3].mT)


def test_moment_maps_follow_new_advance_and_scatter():
    # The cached Aᵀ, A/2, Jᵀ, J/2 are remade when A or J is replaced.
    integration = SpeedIntegration(4, Kinematics((0, 2), (1, 3), 0.1))
    joint = _joint((2,), 4, 2, seed=3)
    integration.moment_terms(*joint)
    other = LinearIntegration(2.0 * integration.advance, 3.0 * integration.scatter, integration.outputs)
    integration.advance, integration.scatter = other.advance, other.scatter
    got = integration.moment_terms(*joint)
    want = other.moment_terms(*(t[:, None] for t in joint))
    for g, w in zip(got, want, strict=True):
        torch.testing.assert_close(g, w.squeeze(1), rtol=1e-14, atol=1e-14)
