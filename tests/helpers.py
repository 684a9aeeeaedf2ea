"""Helpers shared by several test modules (importable as ``tests.helpers``)."""

from __future__ import annotations

import numpy as np

from envs.rewards import SaturatingReward
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
