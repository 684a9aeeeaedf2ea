"""Shared check of the propagators: one rollout of a batched policy (ψ `R x ...`) is R separate rollouts."""

from __future__ import annotations

from collections.abc import Callable

import torch

from qtl.gaussian import Gaussian
from qtl.policies import Policy, batched_policy, restart_state
from qtl.propagation import Propagator

RESTARTS = 3
# Float64: batched and separate rollouts differ only by the order of floating-point operations.
RESTART_RTOL = 1e-10


def spread_restarts(policy: Policy, restarts: int = RESTARTS, seed: int = 0, scale: float = 0.2) -> Policy:
    """A batched copy of ``policy`` whose restarts r > 0 are moved away from restart 0 by ``scale`` · N(0, I)."""
    batched = batched_policy(policy, restarts)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in batched.parameters():
            p[1:].add_(scale * torch.randn(p[1:].shape, generator=gen, dtype=p.dtype))
    return batched


def assert_restarts_equal_separate(make: Callable[[Policy], Propagator], policy: Policy, start: Gaussian,
                                   horizon: int) -> None:
    """V `R` and ∂V_r/∂ψ_r of one batched rollout equal those of R rollouts of the plain policy (1e-10 relative)."""
    batched = spread_restarts(policy)
    values = make(batched).expected_return(start, horizon)
    assert values.shape == (RESTARTS,)
    values.sum().backward()
    for r in range(RESTARTS):
        policy.load_state_dict(restart_state(batched, r))
        policy.zero_grad()
        value = make(policy).expected_return(start, horizon)
        value.backward()
        torch.testing.assert_close(values[r], value, rtol=RESTART_RTOL, atol=0)
        for name, p in policy.named_parameters():
            grad = batched.get_parameter(name).grad[r]
            scale = float(p.grad.abs().max())
            torch.testing.assert_close(grad, p.grad, rtol=RESTART_RTOL, atol=RESTART_RTOL * scale)
    assert not torch.equal(values[0], values[1])  # the restarts really differ


def random_start(models: int, gen: torch.Generator) -> Gaussian:
    """A random 3-D start distribution drawn from ``gen``, its mean repeated per stacked model (`models x 3`)."""
    root = 0.3 * torch.randn(3, 3, generator=gen, dtype=torch.float64)
    mean = 0.3 * torch.randn(3, generator=gen, dtype=torch.float64)
    if models > 1:  # one start per model
        mean = mean.expand(models, 3)
    return Gaussian(mean, root @ root.T + 0.01 * torch.eye(3, dtype=torch.float64))
