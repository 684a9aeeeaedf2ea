"""Per-element failures: a restart whose covariance is not positive-definite is NaN, the others as without it."""

from __future__ import annotations

import math

import pytest
import torch

from qtl.gaussian import cholesky, element_failures, nan_where
from qtl.policies import set_psi, stack_psi
from tests.propagation.failing import BAD, ENGINES, HORIZON, restart_states, solo, system

# The good restarts of a batch against their rollouts alone: the same maths, another batch size.
SOLO_RTOL = 1e-10


def test_cholesky_raises_outside_and_marks_inside():
    """Outside element_failures a failure raises as torch.linalg.cholesky; inside, the element is marked."""
    mat = torch.eye(2, dtype=torch.float64).repeat(3, 2, 1, 1)  # 3 elements x 2 matrices
    mat[1, 0, 1, 1] = -1.0
    with pytest.raises(torch.linalg.LinAlgError, match="not positive-definite"):
        cholesky(mat, inner=1)
    with element_failures() as masks:
        chol, failed = cholesky(mat, inner=1)
    assert [m.tolist() for m in masks] == [[False, True, False]]  # one mask per failing call, `...` of elements
    assert failed.tolist() == [[False, False], [True, True], [False, False]]  # the whole element
    torch.testing.assert_close(chol, torch.eye(2, dtype=torch.float64).expand(3, 2, 2, 2), rtol=0, atol=0)
    value = nan_where(failed, chol.sum((-2, -1)))
    assert value[1].isnan().all() and value[[0, 2]].isfinite().all()


def test_cholesky_where_nothing_fails_is_torch_linalg_cholesky():
    gen = torch.Generator().manual_seed(0)
    root = torch.randn(4, 3, 3, generator=gen, dtype=torch.float64)
    mat = root @ root.mT + 0.1 * torch.eye(3, dtype=torch.float64)
    chol, failed = cholesky(mat)
    assert failed is None and torch.equal(chol, torch.linalg.cholesky(mat))


@pytest.mark.parametrize("moments", ENGINES)
def test_a_failing_restart_is_nan_and_the_others_are_as_without_it(moments):
    """One batched rollout of 3 restarts, restart 1 not positive-definite: NaN there; the others' values and
    gradients are bit for bit those of the batch where restart 1 does not fail, and those of their rollouts alone."""
    policy, propagator, start = system(moments)
    names = ["weight", "bias", "shift"]
    results = {}
    for bad_shift in (-50.0, 0.0):
        states = restart_states(policy, bad_shift)
        plain = set_psi(policy, stack_psi(states, names), (3,))
        try:
            if bad_shift < 0:
                with pytest.raises(torch.linalg.LinAlgError):  # outside element_failures: it raises, as before
                    propagator.expected_return(start, HORIZON)
            with element_failures() as masks:
                values = propagator.expected_return(start, HORIZON)
            values.sum().backward()
            grads = torch.cat([policy.weight.grad.flatten(1), policy.bias.grad.flatten(1)], dim=1)
        finally:
            set_psi(policy, plain)
        results[bad_shift] = values.detach(), grads, bool(masks)
    (values, grads, failed), (clean_values, clean_grads, clean_failed) = results[-50.0], results[0.0]
    assert failed and not clean_failed
    assert math.isnan(values[BAD]) and grads[BAD].isnan().all()
    good = [0, 2]
    assert torch.equal(values[good], clean_values[good]) and torch.equal(grads[good], clean_grads[good])
    for position in good:
        value, grad = solo(policy, propagator, start, restart_states(policy)[position])
        torch.testing.assert_close(values[position], value, rtol=SOLO_RTOL, atol=0)
        torch.testing.assert_close(grads[position], grad, rtol=SOLO_RTOL, atol=SOLO_RTOL * float(grad.abs().max()))
