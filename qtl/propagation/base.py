"""What every propagator is handed and what it gives back: the `Propagator` protocol and `Rollout`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, TypeAlias

import torch
from torch import Tensor

from qtl.gaussian import Gaussian
from qtl.models import GPPosteriorCache
from qtl.policies.base import Policy
from qtl.rewards import ExpectedSaturatingReward


@dataclass(frozen=True)
class Rollout:
    """A predicted trajectory: V = Σ_{t=1..H} E[r(x_t)] and the per-step distributions.

    ``value`` `...` (Eq. 4, successor states x_1..x_H scored; with the task's constraints
    Σ_t S_t (E[r(x_t)] − c_t), :mod:`qtl.constraints`), ``rewards`` E[r(x_t)] `... x H`,
    ``states`` mean `... x (H+1) x D` and cov `... x (H+1) x D x D` (x_0..x_H), ``actions``
    mean `... x H x F` and cov `... x H x F x F` (u_0..u_{H−1}), ``survival`` S_1..S_H `... x H`
    (None: no terminate constraint).
    """

    value: Tensor
    rewards: Tensor
    states: Gaussian
    actions: Gaussian
    survival: Tensor | None = None


class PosteriorSource(Protocol):
    """A fitted GP dynamics model (``DynamicsGP``, ``SparseDynamicsGP``): it hands out its posterior cache."""

    def posterior_cache(self) -> GPPosteriorCache:
        """The training inputs, (K + σ_ε²I)⁻¹, β and θ a propagator needs."""
        ...


# What a propagator accepts as the dynamics: a model, its cache, or caches of equal sizes stacked as `M`.
DynamicsSource: TypeAlias = GPPosteriorCache | Sequence[GPPosteriorCache] | PosteriorSource


class Propagator(Protocol):
    """Long-term prediction of the state distribution under π_ψ and the GP (Eq. 4); both propagators are one."""

    policy: Policy
    reward: ExpectedSaturatingReward
    state_dim: int
    dtype: torch.dtype

    def rollout(self, start: Gaussian, horizon: int) -> Rollout:
        """H steps from N(μ_0, Σ_0): the predicted return and the per-step distributions."""
        ...

    def expected_return(self, start: Gaussian, horizon: int) -> Tensor:
        """V^π(x_0) `...` (Eq. 4), differentiable in ψ: the objective of policy search."""
        ...


class PropagatorFactory(Protocol):
    """What ``instantiate(cfg.propagation)`` gives (a ``_partial_`` config): parts in, a propagator out."""

    def __call__(
        self,
        model: DynamicsSource,
        policy: Policy,
        reward: ExpectedSaturatingReward,
        *,
        angle_dims: Sequence[int] = (),
    ) -> Propagator:
        """A propagator for this model, policy and reward."""
        ...
