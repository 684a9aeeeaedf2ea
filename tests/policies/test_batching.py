"""Restarts as a leading dimension of ψ: a batched policy is R policies, action by action and moment by moment."""

from __future__ import annotations

import itertools

import pytest
import torch

from qtl.gaussian import Gaussian
from qtl.policies import LinearPolicy, Policy, RBFPolicy, batched_policy, restart_state, set_psi, stack_psi
from tests.policies.test_policies import KINDS, make_policy
from tests.propagation.restarts import spread_restarts as spread

DTYPE = torch.float64
RESTARTS = 3
# Batched and per-restart results differ only by the order of floating-point operations.
RTOL, ATOL = 1e-10, 1e-13


def spread_restarts(policy: Policy, restarts: int = RESTARTS, seed: int = 0) -> Policy:
    """A batched copy of ``policy`` whose restarts r > 0 are moved away from restart 0, so that they differ."""
    return spread(policy, restarts, seed, scale=0.3)


def per_restart(batched: Policy, like: Policy, restart: int) -> Policy:
    """Restart ``restart`` of a batched policy as a plain policy (``like`` with its state loaded)."""
    like.load_state_dict(restart_state(batched, restart))
    return like


@pytest.mark.parametrize(("kind", "input_shape"), list(itertools.product(KINDS, [(5, 3), (RESTARTS, 5, 3)])))
def test_batched_actions_equal_per_restart(kind, input_shape):
    """``forward`` of ψ `R x ...` on `S x D` or `R x S x D` features gives `R x S x F`, restart r's actions at r."""
    batched = spread_restarts(make_policy(kind))
    x = torch.randn(input_shape, generator=torch.Generator().manual_seed(1), dtype=DTYPE)
    with torch.no_grad():
        actions = batched(x)
        assert actions.shape == (RESTARTS, 5, 2)
        for r in range(RESTARTS):
            single = per_restart(batched, make_policy(kind), r)
            torch.testing.assert_close(actions[r], single(x[r] if x.dim() == 3 else x), rtol=RTOL, atol=ATOL)


@pytest.mark.parametrize(("kind", "state_batch"), list(itertools.product(KINDS, [(), (RESTARTS,)])))
def test_batched_moments_equal_per_restart(kind, state_batch, cov_factory):
    """``prepare()`` of ψ `R x ...` broadcasts R against the Gaussian input's batch (none, or `R`)."""
    batched = spread_restarts(make_policy(kind))
    gen = torch.Generator().manual_seed(2)
    state = Gaussian(0.5 * torch.randn(*state_batch, 3, generator=gen, dtype=DTYPE),
                     cov_factory(3, 0.6, gen, batch=state_batch))
    with torch.no_grad():
        result = batched.prepare()(state)
        assert result.mean.shape == (RESTARTS, 2) and result.gain.shape == (RESTARTS, 3, 2)
        for r in range(RESTARTS):
            single = per_restart(batched, make_policy(kind), r).moments(state[r] if state_batch else state)
            for got, want in zip((result.mean, result.cov, result.cross_cov, result.gain),
                                 (single.mean, single.cov, single.cross_cov, single.gain), strict=True):
                torch.testing.assert_close(got[r], want, rtol=RTOL, atol=ATOL)


@pytest.mark.parametrize("kind", KINDS)
def test_gradient_of_the_sum_is_each_restarts_own(kind, cov_factory):
    """∂(Σ_r V_r)/∂ψ_r = ∂V_r/∂ψ_r: block-separable, as the joint optimisation of restarts needs."""
    batched = spread_restarts(make_policy(kind))
    gen = torch.Generator().manual_seed(3)
    state = Gaussian(0.5 * torch.randn(3, generator=gen, dtype=DTYPE), cov_factory(3, 0.6, gen))
    out = batched.moments(state)
    (out.mean.sum() + out.cov.sum()).backward()
    for r in range(RESTARTS):
        single = per_restart(batched, make_policy(kind), r)
        moments = single.moments(state)
        (moments.mean.sum() + moments.cov.sum()).backward()
        for name, p in single.named_parameters():
            torch.testing.assert_close(batched.get_parameter(name).grad[r], p.grad, rtol=RTOL, atol=ATOL)


def test_restart_state_round_trip_and_the_original_is_untouched():
    policy = make_policy("squashed-rbf")
    before = {k: v.clone() for k, v in policy.state_dict().items()}
    batched = spread_restarts(policy)
    assert batched.batch_shape == (RESTARTS,) and batched.policy.batch_shape == (RESTARTS,)
    assert policy.batch_shape == () and all(torch.equal(v, before[k]) for k, v in policy.state_dict().items())
    assert all(torch.equal(v, before[k]) for k, v in restart_state(batched, 0).items())  # restart 0: unmoved
    moved = restart_state(batched, 2)
    assert not torch.equal(moved["policy.targets"], before["policy.targets"])
    torch.testing.assert_close(moved["action_bound"], before["action_bound"])  # buffers are not batched


def test_set_psi_swaps_in_place_and_back():
    """The search's way: stacked ψ swapped into the same policy object, then the plain ψ put back."""
    policy = LinearPolicy(3, 2, generator=torch.Generator().manual_seed(0))
    states = [policy.state_dict(), {k: v + 1.0 for k, v in policy.state_dict().items()}]
    plain = set_psi(policy, stack_psi(states, ["weight", "bias"]), (2,))
    assert policy.batch_shape == (2,) and policy.weight.shape == (2, 2, 3) and policy.weight.requires_grad
    x = torch.randn(4, 3, generator=torch.Generator().manual_seed(1), dtype=DTYPE)
    with torch.no_grad():
        shifted = policy(x)[1] - policy(x)[0]
    torch.testing.assert_close(shifted, x.sum(-1, keepdim=True).expand(4, 2) + 1.0)  # (W + 1) x + b + 1
    set_psi(policy, plain)
    assert policy.batch_shape == () and policy.weight is plain["weight"]


def test_bad_batches_are_named():
    policy = RBFPolicy(3, 1, 4, generator=torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="restarts must be >= 1"):
        batched_policy(policy, 0)
    with pytest.raises(ValueError, match="batched already"):
        batched_policy(batched_policy(policy, 2), 2)
    with pytest.raises(ValueError, match="exactly the ψ names"):
        set_psi(policy, {"targets": torch.zeros(2, 4, 1, dtype=DTYPE)}, (2,))
    psi = {name: p.detach().expand(2, *p.shape) for name, p in policy.named_parameters()}
    psi["targets"] = torch.zeros(2, 5, 1, dtype=DTYPE)
    with pytest.raises(ValueError, match="targets must be"):
        set_psi(policy, psi, (2,))
    with pytest.raises(ValueError, match="one restart dimension"):
        restart_state(policy, 0)
