"""Helpers shared by several test modules (importable as ``tests.helpers``)."""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np
import torch
from hydra import compose, initialize_config_module
from omegaconf import DictConfig
from torch import Tensor

from qtl.config import register_configs
from qtl.envs.rewards import SaturatingReward
from qtl.gaussian import Gaussian
from qtl.policies import RBFPolicy, SquashedPolicy
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


def as_overrides(settings: Mapping[str, object]) -> list[str]:
    """Hydra overrides ``key=value`` of ``settings``, booleans spelled as Hydra writes them."""
    return [f"{key}={str(value).lower() if isinstance(value, bool) else value}" for key, value in settings.items()]


# The tiny learning budget of every test that runs the loop, defined once: 6 steps per episode, a
# handful of policy-search and model-fit iterations. The variants below change only what they need.
TINY_BUDGET: dict[str, object] = {
    "task.horizon": 6,
    "task.success.last_steps": 2,
    "task.policy_size": 4,
    "optimizer.max_iter": 2,
    "optimizer.restarts": 1,
    "model.restarts": 1,
    "model.max_iter": 3,
}
# End-to-end runs that set their own episodes and threads (qtl-demo, experiment sweeps).
BUDGET = as_overrides(TINY_BUDGET)
# The CLI's budget in end-to-end tests: one learned episode, one torch thread.
CLI_TINY = ["episodes=1", *BUDGET, "threads=1"]
# The CLI's budget with particle rollouts, searched by Adam (suited to particle objectives) instead of L-BFGS.
PARTICLES_TINY = as_overrides({
    **{key: value for key, value in TINY_BUDGET.items() if key != "optimizer.max_iter"},
    "episodes": 1,
    "threads": 1,
    "optimizer": "adam",
    "optimizer.steps": 3,
    "propagation": "particles",
    "propagation.num_particles": 20,
})
# In-process runs of the loop: two steps longer and two search runs, so that every line of the loop
# runs (figures every episode, restarts), still in seconds.
TINY = as_overrides({
    **TINY_BUDGET,
    "task.horizon": 8,
    "task.success.last_steps": 3,
    "task.policy_size": 5,
    "optimizer.max_iter": 3,
    "optimizer.restarts": 2,
    "model.max_iter": 5,
    "progress": False,
    "figure_every": 1,
    "threads": 1,
})


def train_config(*overrides: str) -> DictConfig:
    """The composed ``train`` config with ``overrides``."""
    register_configs()
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        return compose(config_name="train", overrides=list(overrides))


def tiny_config(*overrides: str) -> DictConfig:
    """The composed ``train`` config with the TINY budget and ``overrides``."""
    return train_config(*TINY, *overrides)


def squashed_rbf_parts(gp_factory: Callable, state_dim: int, angle_dims: tuple[int, ...], num_basis: int,
                       seeds: tuple[int, int]) -> tuple:
    """A toy GP (``gp_factory``, 40 points, 1 action), a squashed RBF policy on its features, a quadratic reward.

    ``seeds``: of the GP's data and of the policy's support points and targets.
    """
    gp = gp_factory(40, state_dim, 1, angle_dims, seed=seeds[0])
    gen = torch.Generator().manual_seed(seeds[1])
    targets = torch.randn(num_basis, 1, generator=gen, dtype=torch.float64)
    policy = SquashedPolicy(RBFPolicy(state_dim + len(angle_dims), 1, num_basis, targets=targets, generator=gen), 2.0)
    return gp, policy, quadratic_reward(state_dim, angle_dims)


# A task file for gymnasium's Pendulum-v1 as a user writes one (docs/guide/byo-env.md), on the tiny budget; the
# reward's target and weight are left to fill in.
PENDULUM_TASK_TEMPLATE = """\
name: pendulum
env:
  id: Pendulum-v1
horizon: 6
angle_dims: []
policy_size: 4
start:
  mean: [1.0, 0.0, 0.0]
  std: [0.05, 0.05, 0.1]
reward:
  angle_dims: []
  target: {target}
  weight: {weight}
  width: 0.5
success:
  threshold: 0.2
  last_steps: 2
"""
PENDULUM_TASK = PENDULUM_TASK_TEMPLATE.format(target="[1.0, 0.0, 0.0]",
                                              weight="[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]]")
