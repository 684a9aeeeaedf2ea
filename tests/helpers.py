"""Helpers shared by several test modules (importable as ``tests.helpers``)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from hydra import compose, initialize_config_module
from omegaconf import DictConfig
from torch import Tensor

from envs.rewards import SaturatingReward
from qtl.config import register_configs
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


# A budget that exercises every line of the loop in seconds: short horizon, few evaluations.
TINY = [
    "task.horizon=8",
    "task.success.last_steps=3",
    "task.policy_size=5",
    "optimizer.max_iter=3",
    "optimizer.restarts=2",
    "model.restarts=1",
    "model.max_iter=5",
    "progress=false",
    "figure_every=1",
    "threads=1",
]


def tiny_config(*overrides: str) -> DictConfig:
    """The composed ``train`` config with the TINY budget and ``overrides``."""
    register_configs()
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        return compose(config_name="train", overrides=[*TINY, *overrides])


# The CLI's budget in end-to-end tests: one learned episode of 6 steps, a handful of evaluations.
CLI_TINY = [
    "episodes=1",
    "task.horizon=6",
    "task.success.last_steps=2",
    "task.policy_size=4",
    "optimizer.max_iter=2",
    "optimizer.restarts=1",
    "model.restarts=1",
    "model.max_iter=3",
    "threads=1",
]
