"""Which ψ a run leaves: the best seen (keep="best"), the last valued afresh, or the best of validated snapshots."""

from __future__ import annotations

import math

import pytest
import torch

from qtl import health
from qtl.policy_search.keep import SNAPSHOTS, snapshot_due
from tests.policy_search.problems import Point, adam, bowl


class SpikedBowl:
    """``bowl`` with +5 at one call (a lucky noisy value): what keep="best" keeps and keep="last" does not."""

    def __init__(self, point: Point, spike_at: int = 3) -> None:
        self.point, self.spike_at = point, spike_at
        self.points: list[torch.Tensor] = []
        self.values: list[float] = []

    def __call__(self) -> torch.Tensor:
        self.points.append(self.point.x.detach().clone())
        value = bowl(self.point) + (5.0 if len(self.points) == self.spike_at else 0.0)
        self.values.append(float(value.detach()))
        return value


def test_keep_last_leaves_the_final_psi_valued_afresh():
    point = Point([0.0, 0.0])
    objective = SpikedBowl(point)
    result = adam(steps=50, lr=0.05, keep="last")(point, objective)
    assert result.evaluations == len(objective.values) == 51  # every step, and one more at the final ψ
    assert torch.equal(point.x.detach(), objective.points[-1])  # the final ψ ...
    assert not torch.equal(objective.points[-1], objective.points[-2])  # ... after the last step
    assert result.value == objective.values[-1] == pytest.approx(float(bowl(point).detach()))  # ... its fresh value
    assert result.value < max(objective.values) and result.run_values == [result.value]


def test_keep_best_leaves_the_best_value_seen():
    point = Point([0.0, 0.0])
    objective = SpikedBowl(point)
    result = adam(steps=50, lr=0.05)(point, objective)
    assert result.evaluations == len(objective.values) == 50
    assert result.value == max(objective.values) == objective.values[2]  # the spike
    assert torch.equal(point.x.detach(), objective.points[2])


def test_keep_last_with_sequential_restarts_keeps_the_best_final_value():
    point = Point([0.0, 0.0])
    objective = SpikedBowl(point, spike_at=2)
    result = adam(steps=20, lr=0.05, restarts=2, perturbation=0.5, keep="last", batched=False)(
        point, objective, generator=torch.Generator().manual_seed(0))
    finals = [objective.values[20], objective.values[41]]  # each run's extra evaluation
    assert result.run_values == finals and result.value == max(finals) and result.evaluations == 42
    assert torch.equal(point.x.detach(), objective.points[20 if finals[0] >= finals[1] else 41])


class RiseAndFall:
    """Adam's steps climb ``point.x[0]`` at a constant rate (the gradient is constant); the value, peaked at 1,
    is what the search reports: it rises along the run and falls again, as a noisy search that leaves its optimum.
    ``fail_above``: the value is NaN where x[0] exceeds it (a ψ that fails to evaluate)."""

    def __init__(self, point: Point, fail_above: float | None = None) -> None:
        self.point, self.fail_above = point, fail_above
        self.points: list[torch.Tensor] = []

    def __call__(self) -> torch.Tensor:
        x = self.point.x[0]
        self.points.append(self.point.x.detach().clone())
        value = x - x.detach() - (x.detach() - 1.0).square()
        if self.fail_above is not None and float(x) > self.fail_above:
            value = value * math.nan
        return value


def test_snapshots_fall_every_steps_over_snapshots_steps_and_not_at_the_end():
    assert [s for s in range(100) if snapshot_due("validated", s, 100)] == list(range(4, 99, 5))[:SNAPSHOTS - 1]
    assert [s for s in range(7) if snapshot_due("validated", s, 7)] == [0, 1, 2, 3, 4, 5]  # every step: short runs
    assert not any(snapshot_due(keep, s, 100) for keep in ("best", "last") for s in range(100))


def test_keep_validated_leaves_the_best_snapshot_valued_afresh():
    """100 steps of 0.02 take x from 0 to 2; snapshots every 5 steps; the one at x = 1 (step 50) is kept."""
    point = Point([0.0, 0.0])
    objective = RiseAndFall(point)
    result = adam(steps=100, lr=0.02, keep="validated")(point, objective)
    assert result.evaluations == len(objective.points) == 100 + 21  # every step; the start, 19 snapshots, the final ψ
    assert float(point.x[0]) == pytest.approx(1.0, abs=1e-6) and result.value == pytest.approx(0.0, abs=1e-10)
    last = adam(steps=100, lr=0.02, keep="last")(Point([0.0, 0.0]), RiseAndFall(Point([0.0, 0.0])))
    assert last.value < -0.9  # keep="last" leaves x ≈ 2, where the value is ≈ −1


def test_keep_validated_passes_over_a_snapshot_that_fails():
    point = Point([0.0, 0.0])
    health.take()
    result = adam(steps=100, lr=0.02, keep="validated")(point, RiseAndFall(point, fail_above=1.5))
    counts = health.take()
    # The run stops at its first NaN (x > 1.5, step 76); its snapshots (steps 5-75) are valued and x = 1 is kept.
    assert float(point.x[0]) == pytest.approx(1.0, abs=1e-6) and result.value == pytest.approx(0.0, abs=1e-10)
    assert counts[health.SEARCH_STOPPED] == 1 and counts[health.NONFINITE] == 1


def test_keep_validated_never_leaves_a_worse_psi_than_its_start():
    """Started at the peak (x = 1), every step makes the value worse: the start, valued afresh, is kept."""
    point = Point([1.0, 0.0])
    result = adam(steps=40, lr=0.02, keep="validated")(point, RiseAndFall(point))
    assert float(point.x[0]) == 1.0 and result.value == 0.0
