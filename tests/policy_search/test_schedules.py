"""MC-PILCO's schedule: dropout during the search, and at each plateau a lower learning rate and dropout."""

from __future__ import annotations

import logging
import math

import pytest
import torch

from qtl.policies import RBFNetwork
from tests.policy_search.problems import LR, STAGES, adam, scheduled_search, tiny_network


class FlatObjective:
    """V = ``slope`` · Σ w + ``scale`` · ε_call (a flat, noisy objective); records the policy's dropout and ψ per call.

    ``fail_at``: the call (1-based) whose value is NaN.
    """

    def __init__(self, policy: RBFNetwork, slope: float = 0.1, scale: float = 1.0, fail_at: int | None = None) -> None:
        self.policy, self.slope, self.fail_at = policy, slope, fail_at
        self.noise = scale * torch.randn(5000, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
        self.dropouts: list[float] = []
        self.weights: list[torch.Tensor] = []
        self.values: list[float] = []
        self.grad_enabled: list[bool] = []

    def __call__(self) -> torch.Tensor:
        call = len(self.values)
        self.dropouts.append(self.policy.dropout)
        self.weights.append(self.policy.weights.detach().clone())
        self.grad_enabled.append(torch.is_grad_enabled())
        value = self.slope * self.policy.weights.sum() + self.noise[call]
        if self.fail_at is not None and call + 1 == self.fail_at:
            value = value * math.nan
        self.values.append(float(value.detach()))
        return value


def test_a_flat_noisy_objective_walks_the_schedule_and_stops_early(caplog):
    """Each plateau halves the learning rate and lowers the dropout; a plateau at lr_min stops the search."""
    policy = tiny_network()
    objective = FlatObjective(policy)
    with caplog.at_level(logging.INFO, logger="qtl.policy_search"):
        result = scheduled_search()(policy, objective, generator=torch.Generator().manual_seed(0))
    calls = len(objective.values)
    assert result.evaluations == calls < 1000  # stopped early (the last call: keep="last"'s evaluation)
    # A constant gradient makes each Adam step move every weight by its learning rate (to 1e-5 relative).
    steps = [float((b - a)[0, 0]) for a, b in zip(objective.weights[:-1], objective.weights[1:], strict=True)]
    stages = []
    for lr, dropout in zip(steps, objective.dropouts[:-1], strict=True):  # the dropout a step's evaluation saw
        stage = next(s for s in STAGES if s[1] == dropout)
        assert lr == pytest.approx(stage[0], rel=1e-4), (lr, dropout)
        if not stages or stages[-1] != stage:
            stages.append(stage)
    assert stages == STAGES  # every stage, in order
    assert objective.dropouts[-1] == 0.0 and not objective.grad_enabled[-1]  # the final value: no dropout, no grad
    assert policy.dropout == 0.0
    messages = [r.getMessage() for r in caplog.records]
    assert any("plateau at lr 0.0025" in m and "stopped" in m for m in messages)
    assert sum("plateau after" in m for m in messages) == 2


def test_a_constant_objective_stops_after_three_plateaus_exactly():
    """ΔV = 0: plateaus at monitor steps 6, 12, 18 (window 5, min_steps 5): evaluations 7, 13, 19; then one more."""
    policy = tiny_network()
    dropouts = []

    def objective() -> torch.Tensor:
        dropouts.append(policy.dropout)
        return 0.0 * policy.weights.sum() + 1.0

    result = scheduled_search(plateau={"ema": 0.9, "threshold": 0.08, "window": 5, "min_steps": 5})(policy, objective)
    assert result.evaluations == len(dropouts) == 20 and result.value == 1.0
    assert dropouts == [0.25] * 7 + [0.125] * 6 + [0.0] * 7
    assert result.run_evaluations == [20]


def test_dropout_is_reset_when_the_objective_fails_midway():
    policy = tiny_network()
    objective = FlatObjective(policy, fail_at=5)
    result = scheduled_search()(policy, objective)
    assert objective.dropouts == [0.25] * 5 and policy.dropout == 0.0
    assert result.evaluations == 5 and result.value == max(objective.values[:4])  # the best finite ψ is kept
    assert torch.equal(policy.weights.detach(), objective.weights[objective.values.index(result.value)])


def test_without_a_plateau_rule_dropout_stays_for_all_steps_and_is_reset():
    policy = tiny_network()
    objective = FlatObjective(policy)
    result = adam(steps=12, lr=LR, dropout=0.3)(policy, objective)
    assert objective.dropouts == [0.3] * 12 and policy.dropout == 0.0 and result.evaluations == 12


def test_a_dropout_search_is_reproducible_from_its_generator():
    """The masks come from the search's generator: the same seed, the same ψ; another seed, another ψ."""
    features = torch.randn(30, 2, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    target = features[:, :1].sin()

    def search(seed: int) -> torch.Tensor:
        policy = tiny_network()
        adam(steps=15, lr=0.05, dropout=0.25, keep="last")(
            policy, lambda: -(policy(features) - target).square().mean(), generator=torch.Generator().manual_seed(seed))
        return torch.cat([p.detach().flatten() for p in policy.parameters()])

    first = search(0)
    assert torch.equal(first, search(0))
    assert not torch.equal(first, search(1))
