"""Helpers shared by several test modules (importable as ``tests.helpers``)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from envs.rewards import SaturatingReward
from qtl.gaussian import Gaussian
from qtl.rewards import ExpectedSaturatingReward


def quadratic_reward(state_dim: int, angle_dims=(), width: float = 1.5) -> ExpectedSaturatingReward:
    """A saturating reward around the origin on all augmented coordinates."""
    aug = state_dim + len(angle_dims)
    target = np.zeros(aug)
    for k, _ in enumerate(angle_dims):
        target[state_dim - len(angle_dims) + 2 * k + 1] = 1.0  # cos θ = 1 at θ = 0
    spec = SaturatingReward(
        state_dim=state_dim,
        angle_dims=tuple(angle_dims),
        target=tuple(target),
        weight=tuple(map(tuple, np.eye(aug))),
        width=width,
    )
    return ExpectedSaturatingReward.from_spec(spec)


def gradcheck_value_wrt_policy_and_start(policy: torch.nn.Module, value: Callable[[Gaussian], Tensor],
                                         start: Gaussian) -> bool:
    """``torch.autograd.gradcheck`` of ``value(N(mean, start.cov))`` w.r.t. the start mean and every ψ tensor."""
    names = [name for name, _ in policy.named_parameters()]
    psi = tuple(p.detach().clone().requires_grad_() for p in policy.parameters())

    class Value(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.policy = policy

        def forward(self, mean: Tensor) -> Tensor:
            return value(Gaussian(mean, start.cov))

    def call(mean: Tensor, *params: Tensor) -> Tensor:
        swapped = {f"policy.{n}": p for n, p in zip(names, params, strict=True)}
        return torch.func.functional_call(Value(), swapped, (mean,))

    return torch.autograd.gradcheck(call, (start.mean.clone().requires_grad_(), *psi))
