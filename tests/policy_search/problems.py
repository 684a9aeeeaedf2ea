"""Toy problems of the policy search tests: a bowl, a valley beside an invalid region, a small real rollout."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import torch
from torch import nn

from qtl.gaussian import Gaussian, GaussianMap
from qtl.plateau import PlateauRule
from qtl.policies import Policy, RBFNetwork, RBFPolicy, SquashedPolicy
from qtl.policy_search import AdamSearch, AdamSettings, LBFGSSearch, LBFGSSettings
from qtl.propagation import MomentMatching
from tests.helpers import quadratic_reward

TARGET = torch.tensor([1.0, -2.0], dtype=torch.float64)


def lbfgs(**settings) -> LBFGSSearch:
    """An L-BFGS search with these settings."""
    return LBFGSSearch(LBFGSSettings(**settings))


def adam(**settings) -> AdamSearch:
    """An Adam search with these settings."""
    return AdamSearch(AdamSettings(**settings))


class Point(nn.Module):
    def __init__(self, start: list[float]) -> None:
        super().__init__()
        self.x = nn.Parameter(torch.tensor(start, dtype=torch.float64))


def bowl(point: Point) -> torch.Tensor:
    """A concave objective with its maximum 1 at (1, −2)."""
    return 1.0 - ((point.x - TARGET) ** 2).sum()


class BowlPolicy(Policy):
    """A toy policy: ψ = (``x`` `2`, trainable; ``tag`` `1`, fixed, perturbed per restart so that restarts differ)."""

    input_dim = output_dim = 2

    def __init__(self, start: list[float]) -> None:
        super().__init__()
        self.x = nn.Parameter(torch.tensor(start, dtype=torch.float64))
        self.tag = nn.Parameter(torch.zeros(1, dtype=torch.float64), requires_grad=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Not used."""
        raise NotImplementedError

    def prepare(self) -> GaussianMap:
        """Not used."""
        raise NotImplementedError

    def value(self) -> torch.Tensor:
        """1 − ‖x − (1, −2)‖²: `R` when ψ are batched, a scalar otherwise."""
        return 1.0 - (self.x - TARGET).square().sum(-1)


class ValleyPolicy(BowlPolicy):
    """The toy policy with a curved valley (maximum 1 at (1, 1)) beside an invalid region where V is NaN."""

    def value(self) -> torch.Tensor:
        """1 − (1 − x₀)² − 10 (x₁ − x₀²)², NaN where x₀ > 0.6 and x₁ < 0.3: `R` batched, a scalar otherwise."""
        x0, x1 = self.x[..., 0], self.x[..., 1]
        value = 1.0 - (1.0 - x0).square() - 10.0 * (x1 - x0.square()).square()
        return torch.where(invalid(self.x), math.nan, value)


def invalid(x: torch.Tensor) -> torch.Tensor:
    """Where ValleyPolicy's V is NaN, for x `... x 2`."""
    return (x[..., 0] > 0.6) & (x[..., 1] < 0.3)


def moment_matching_problem(gp_factory) -> tuple[SquashedPolicy, Callable[[], torch.Tensor]]:
    """A squashed RBF policy and V(ψ) of a 5-step moment-matching rollout of a small GP (deterministic)."""
    gp = gp_factory(30, 3, 1, (1,), seed=22)
    gen = torch.Generator().manual_seed(23)
    policy = SquashedPolicy(RBFPolicy(4, 1, 8, targets=torch.randn(8, 1, generator=gen, dtype=torch.float64),
                                      generator=gen), 2.0)
    propagator = MomentMatching(gp, policy, quadratic_reward(3, (1,)), angle_dims=(1,))
    start = Gaussian(torch.tensor([0.1, 0.2, -0.1], dtype=torch.float64), 0.01 * torch.eye(3, dtype=torch.float64))
    return policy, functools.partial(propagator.expected_return, start, 5)


def tiny_network() -> RBFNetwork:
    """A 3-basis RBF network on 2-D features, one action: a policy that can drop its basis functions."""
    gen = torch.Generator().manual_seed(0)
    return RBFNetwork(torch.randn(3, 2, generator=gen, dtype=torch.float64),
                      torch.randn(3, 1, generator=gen, dtype=torch.float64), torch.ones(1, 2, dtype=torch.float64))


def trainable_psi(policy: Policy) -> torch.Tensor:
    """The trainable ψ flattened per restart: `*batch_shape x n` (L-BFGS's point)."""
    return torch.cat([p.detach().flatten(start_dim=len(policy.batch_shape))
                      for p in policy.parameters() if p.requires_grad], -1)


def points_per_restart(search, policy: Policy, objective: Callable[[], torch.Tensor],
                       seed: int) -> tuple[list[list[torch.Tensor]], object]:
    """Each restart's evaluated points, in order, and the search's result (no restart may fail)."""
    seen = []

    def recording() -> torch.Tensor:
        seen.append(trainable_psi(policy).clone())
        return objective()

    result = search(policy, recording, generator=torch.Generator().manual_seed(seed))
    counts = result.run_evaluations
    points: list[list[torch.Tensor]] = [[] for _ in counts]
    if not search.batched:  # the runs one after the other
        for restart, count in enumerate(counts):
            points[restart], seen = seen[:count], seen[count:]
        return points, result
    for round_, stacked in enumerate(seen):  # round k holds the restarts with more than k evaluations, in order
        active = [restart for restart, count in enumerate(counts) if count > round_]
        assert stacked.shape[0] == len(active), "a restart that stopped did not leave the batch"
        for row, restart in enumerate(active):
            points[restart].append(stacked[row])
    return points, result


# -- MC-PILCO's schedule ------------------------------------------------------------------------------

LR, LR_MIN = 0.01, 0.0025
# The schedule's values at its three stages: Adam's learning rate and the policy dropout.
STAGES = [(0.01, 0.25), (0.005, 0.125), (0.0025, 0.0)]


def scheduled_search(**kwargs) -> AdamSearch:
    """MC-PILCO's schedule (lr 0.01 → 0.005 → 0.0025, dropout 0.25 → 0.125 → 0) with a short plateau rule."""
    settings = {"steps": 1000, "lr": LR, "keep": "last", "dropout": 0.25, "dropout_reduction": 0.125,
                "plateau": PlateauRule(ema=0.95, threshold=0.08, window=20, min_steps=20), "lr_reduction": 0.5,
                "lr_min": LR_MIN, **kwargs}
    return adam(**settings)
