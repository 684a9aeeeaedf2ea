"""Policy search: finds the maximum, keeps the best ψ across restarts, survives invalid ψ; restarts batched.

Batched L-BFGS runs each restart's own L-BFGS in lockstep: per restart it is the sequential search.
"""

from __future__ import annotations

import functools
import itertools
import logging
import math
from collections.abc import Callable

import pytest
import torch
from hydra.utils import instantiate
from torch import nn

from qtl import health
from qtl.build import build
from qtl.errors import NonFiniteObjective, UserError
from qtl.gaussian import Gaussian, GaussianMap
from qtl.plateau import PlateauRule
from qtl.policies import Policy, RBFNetwork, RBFPolicy, SquashedPolicy
from qtl.policy_search import AdamSearch, LBFGSSearch
from qtl.propagation import MomentMatching
from tests.helpers import quadratic_reward, train_config


class Point(nn.Module):
    def __init__(self, start: list[float]) -> None:
        super().__init__()
        self.x = nn.Parameter(torch.tensor(start, dtype=torch.float64))


def bowl(point: Point) -> torch.Tensor:
    """A concave objective with its maximum 1 at (1, −2)."""
    return 1.0 - ((point.x - torch.tensor([1.0, -2.0], dtype=torch.float64)) ** 2).sum()


@pytest.mark.parametrize("search", [LBFGSSearch(max_iter=50, restarts=2), AdamSearch(steps=400, lr=0.05)])
def test_finds_the_maximum_and_leaves_it_in_the_policy(search):
    point = Point([0.0, 0.0])
    result = search(point, lambda: bowl(point), generator=torch.Generator().manual_seed(0))
    assert result.value == pytest.approx(1.0, abs=1e-4)
    torch.testing.assert_close(point.x.detach(), torch.tensor([1.0, -2.0], dtype=torch.float64), atol=1e-2, rtol=0)
    assert result.evaluations > 0 and len(result.run_values) == search.restarts


def test_invalid_region_stops_the_run_but_keeps_the_best_point_seen():
    point = Point([0.0, 0.0])

    def objective() -> torch.Tensor:
        if point.x[0] > 0.5:  # the propagation "breaks down" past x0 = 0.5
            raise torch.linalg.LinAlgError("not positive-definite")
        return bowl(point)

    result = LBFGSSearch(max_iter=50, restarts=1)(point, objective)
    assert math.isfinite(result.value) and point.x[0] <= 0.5
    assert result.evaluations >= 2  # the failed evaluation counts too
    assert result.value == pytest.approx(float(bowl(point)))


def test_nan_everywhere_is_reported():
    point = Point([0.0, 0.0])
    health.take()
    with pytest.raises(NonFiniteObjective, match="no policy search run"):
        LBFGSSearch(max_iter=5, restarts=2)(point, lambda: point.x.sum() * math.nan)
    counts = health.take()  # each run's first evaluation is NaN: it stops there
    assert counts[health.NONFINITE] == 2 and counts[health.SEARCH_STOPPED] == 2 and counts[health.LINALG] == 0


def test_a_failed_factorisation_is_counted_apart_from_a_nan():
    point = Point([0.0, 0.0])

    def objective() -> torch.Tensor:
        raise torch.linalg.LinAlgError("not positive-definite")

    health.take()
    with pytest.raises(NonFiniteObjective, match="no policy search run"):
        AdamSearch(steps=5, restarts=3)(point, objective)
    assert health.take() == {**dict.fromkeys(health.EVENTS, 0), health.LINALG: 3, health.SEARCH_STOPPED: 3}


def test_bad_settings_are_named():
    with pytest.raises(ValueError, match="restarts must be >= 1"):
        LBFGSSearch(restarts=0)
    with pytest.raises(ValueError, match="max_iter must be >= 1"):
        LBFGSSearch(max_iter=0)
    with pytest.raises(ValueError, match="steps must be >= 1 and lr > 0"):
        AdamSearch(lr=0.0)


# -- batched restarts ---------------------------------------------------------------------------------

TARGET = torch.tensor([1.0, -2.0], dtype=torch.float64)


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


def first_points(search, policy, objective, seed=0) -> list[torch.Tensor]:
    """ψ (all of it) at the first evaluation of every restart, and the search's result."""
    seen, firsts = [], []

    def recording() -> torch.Tensor:
        psi = torch.cat([p.detach().flatten(start_dim=len(policy.batch_shape)) for p in policy.parameters()], -1)
        seen.append(psi.clone())
        return objective()

    result = search(policy, recording, generator=torch.Generator().manual_seed(seed))
    if search.batched:
        firsts = list(seen[0])
    else:  # the fixed tag (ψ's last entry) differs between runs: a run starts where it changes
        firsts = [psi for i, psi in enumerate(seen) if i == 0 or not torch.equal(seen[i - 1][-1:], psi[-1:])]
    return firsts, result


@pytest.mark.parametrize("make", [lambda b: LBFGSSearch(max_iter=5, restarts=3, perturbation=0.5, batched=b),
                                  lambda b: AdamSearch(steps=5, restarts=3, perturbation=0.5, batched=b)])
def test_batched_starts_where_the_sequential_search_starts(make):
    """Restart 0 from the current ψ, restart r > 0 from the same perturbation (same generator draws, same order)."""
    starts = {}
    for batched in (False, True):
        policy = BowlPolicy([0.0, 0.0])
        starts[batched], _ = first_points(make(batched), policy, policy.value)
    assert len(starts[True]) == len(starts[False]) == 3
    for sequential, batched in zip(starts[False], starts[True], strict=True):
        assert torch.equal(sequential, batched)
    assert not torch.equal(starts[True][1], starts[True][2])


@pytest.mark.parametrize("search", [LBFGSSearch(max_iter=30, restarts=3, batched=True),
                                    AdamSearch(steps=300, lr=0.05, restarts=3, batched=True)])
def test_batched_search_finds_the_maximum_and_leaves_the_best_restart(search):
    policy = BowlPolicy([0.0, 0.0])
    result = search(policy, policy.value, generator=torch.Generator().manual_seed(0))
    assert policy.batch_shape == () and policy.x.shape == (2,)  # the plain policy again
    assert result.value == pytest.approx(1.0, abs=1e-4) and result.value == max(result.run_values)
    assert result.value == pytest.approx(float(policy.value()), abs=0, rel=0)  # the best ψ is the one left
    assert len(result.run_values) == 3 and result.evaluations == sum(result.run_evaluations)
    assert result.rollouts == max(result.run_evaluations)  # one batched rollout per round, restarts in lockstep


def moment_matching_problem(gp_factory) -> tuple[SquashedPolicy, Callable[[], torch.Tensor]]:
    """A squashed RBF policy and V(ψ) of a 5-step moment-matching rollout of a small GP (deterministic)."""
    gp = gp_factory(30, 3, 1, (1,), seed=22)
    gen = torch.Generator().manual_seed(23)
    policy = SquashedPolicy(RBFPolicy(4, 1, 8, targets=torch.randn(8, 1, generator=gen, dtype=torch.float64),
                                      generator=gen), 2.0)
    propagator = MomentMatching(gp, policy, quadratic_reward(3, (1,)), angle_dims=(1,))
    start = Gaussian(torch.tensor([0.1, 0.2, -0.1], dtype=torch.float64), 0.01 * torch.eye(3, dtype=torch.float64))
    return policy, functools.partial(propagator.expected_return, start, 5)


def test_batched_search_of_a_real_rollout_improves_it(gp_factory):
    """Moment matching, squashed RBF policy: the batched search improves V and leaves the best restart's ψ."""
    policy, objective = moment_matching_problem(gp_factory)
    with torch.no_grad():
        before = float(objective())
    ticks = []
    result = LBFGSSearch(max_iter=4, restarts=2, batched=True)(
        policy, objective, generator=torch.Generator().manual_seed(1), tick=lambda: ticks.append(1))
    with torch.no_grad():
        after = float(objective())
    assert result.value > before and result.value == max(result.run_values)
    assert after == pytest.approx(result.value, rel=1e-12, abs=0)  # batched and plain rollouts: round-off apart
    assert result.rollouts == len(ticks) <= 4 and result.evaluations == 2 * result.rollouts


@pytest.mark.parametrize("failure", ["nan", "linalg"])
@pytest.mark.parametrize("make", [lambda: LBFGSSearch(max_iter=40, restarts=3, perturbation=0.5, batched=True),
                                  lambda: AdamSearch(steps=200, lr=0.05, restarts=3, perturbation=0.5, batched=True)])
def test_a_restart_that_fails_is_dropped_and_the_others_go_on(make, failure):
    """From its 2nd evaluation on, one restart's value is NaN (or its rollout raises): it stops, the others converge."""
    search = make()
    policy = BowlPolicy([0.0, 0.0])
    tags = [float(state["tag"]) for state in search.starting_states(policy, torch.Generator().manual_seed(0))]
    bad_tag = max(tags)
    bad = tags.index(bad_tag)
    calls = 0

    def objective() -> torch.Tensor:
        nonlocal calls
        calls += 1
        value = policy.value()
        hit = (policy.tag == bad_tag).flatten(start_dim=len(policy.batch_shape)).any(-1)
        if calls > 1 and bool(hit.any()):
            if failure == "linalg":
                raise torch.linalg.LinAlgError("not positive-definite")
            value = torch.where(hit, math.nan, value)
        return value

    health.take()
    result = search(policy, objective, generator=torch.Generator().manual_seed(0))
    counts = health.take()
    assert counts[health.SEARCH_STOPPED] == 1  # the one restart, counted once
    assert counts[health.NONFINITE if failure == "nan" else health.LINALG] >= 1
    assert counts[health.LINALG if failure == "nan" else health.NONFINITE] == 0
    assert math.isfinite(result.run_values[bad]) and result.run_values[bad] < 1.0 - 1e-3  # stopped early, best kept
    others = [v for r, v in enumerate(result.run_values) if r != bad]
    assert others == pytest.approx([1.0, 1.0], abs=1e-4)  # the others went on to the maximum
    assert result.value == max(others) and float(policy.tag) != bad_tag
    assert result.evaluations < 3 * result.rollouts  # the dropped restart stopped counting


def trainable_psi(policy: Policy) -> torch.Tensor:
    """The trainable ψ flattened per restart: `*batch_shape x n` (L-BFGS's point)."""
    return torch.cat([p.detach().flatten(start_dim=len(policy.batch_shape))
                      for p in policy.parameters() if p.requires_grad], -1)


def points_per_restart(search: LBFGSSearch, policy: Policy, objective: Callable[[], torch.Tensor],
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


# Points of a batched and a sequential L-BFGS run agree to this, relative to their norm (seen: ~1e-10).
POINT_RTOL = 1e-8


def test_batched_lbfgs_runs_each_restart_as_the_sequential_search(gp_factory):
    """Lockstep L-BFGS (moment matching): per restart the same points, evaluations and best V as torch's LBFGS alone."""
    runs = {}
    for batched in (False, True):
        policy, objective = moment_matching_problem(gp_factory)
        search = LBFGSSearch(max_iter=12, restarts=3, perturbation=1.0, batched=batched)
        points, result = points_per_restart(search, policy, objective, seed=1)
        runs[batched] = (points, result, trainable_psi(policy))
    (seq_points, seq, seq_psi), (bat_points, bat, bat_psi) = runs[False], runs[True]
    assert bat.run_evaluations == seq.run_evaluations and len(set(seq.run_evaluations)) > 1  # restarts stop apart
    assert bat.evaluations == seq.evaluations == seq.rollouts == sum(seq.run_evaluations)
    assert bat.rollouts == max(bat.run_evaluations)
    # Batched and plain rollouts differ by round-off (~1e-15), which L-BFGS's updates amplify a little.
    for restart, (want, got) in enumerate(zip(seq_points, bat_points, strict=True)):
        for i, (w, g) in enumerate(zip(want, got, strict=True)):
            assert (g - w).norm() <= POINT_RTOL * w.norm(), f"restart {restart}, evaluation {i}"
    assert bat.run_values == pytest.approx(seq.run_values, rel=1e-9, abs=0)
    assert bat.value == pytest.approx(seq.value, rel=1e-9, abs=0)
    assert (bat_psi - seq_psi).norm() <= POINT_RTOL * seq_psi.norm()  # the same best ψ left in the policy


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


def test_lbfgs_retreats_from_an_invalid_region_and_goes_on_alone_or_batched():
    """A restart whose line search steps into the invalid region retreats halfway back (again and again) and goes
    on to the maximum instead of stopping there; alone or batched, the same points."""
    results = {}
    for batched in (False, True):
        policy = ValleyPolicy([-1.0, 0.5])
        search = LBFGSSearch(max_iter=30, restarts=4, perturbation=0.5, batched=batched)
        health.take()
        points, result = points_per_restart(search, policy, policy.value, seed=2)
        results[batched] = (points, result, health.take())
    (seq_points, seq, seq_counts), (bat_points, bat, bat_counts) = results[False], results[True]
    assert bat.run_evaluations == seq.run_evaluations and bat.run_values == seq.run_values
    assert bat.value == seq.value and seq_counts == bat_counts
    for want, got in zip(seq_points, bat_points, strict=True):
        assert len(got) == len(want) and all(torch.equal(g, w) for g, w in zip(got, want, strict=True))
    retreated = [r for r, restart in enumerate(seq_points) if any(bool(invalid(p)) for p in restart)]
    assert retreated  # some restarts stepped into the invalid region ...
    assert seq_counts[health.NONFINITE] >= len(retreated) and seq_counts[health.SEARCH_STOPPED] == 0
    assert all(not bool(invalid(restart[-1])) for restart in seq_points)  # ... and left it
    assert seq.run_values == pytest.approx([1.0] * 4, abs=1e-4)  # every restart reached the maximum


def test_lbfgs_stops_where_no_valid_step_is_left():
    """From a point whose every step along the search direction is invalid, the run stops there, counted once."""
    policy = ValleyPolicy([0.55, 0.2])  # the valley's ascent leads straight into x₀ > 0.6 with x₁ < 0.3

    def objective() -> torch.Tensor:
        value = policy.value()
        moved = (policy.x - torch.tensor([0.55, 0.2], dtype=policy.x.dtype)).abs().max() > 0
        return torch.where(moved, math.nan, value)  # only the start is valid

    health.take()
    result = LBFGSSearch(max_iter=10, restarts=1)(policy, objective)
    counts = health.take()
    assert counts[health.SEARCH_STOPPED] == 1 and counts[health.NONFINITE] >= 2
    assert result.value == pytest.approx(float(ValleyPolicy([0.55, 0.2]).value()))
    torch.testing.assert_close(policy.x.detach(), torch.tensor([0.55, 0.2], dtype=policy.x.dtype))


def test_batched_adam_follows_each_restarts_own_path():
    """Adam acts per element: the batched search ends where the sequential one ends (round-off apart)."""
    found = {}
    for batched in (False, True):
        policy = BowlPolicy([0.0, 0.0])
        search = AdamSearch(steps=20, lr=0.05, restarts=3, perturbation=0.5, batched=batched)
        result = search(policy, policy.value, generator=torch.Generator().manual_seed(0))
        found[batched] = (result, policy.x.detach().clone())
    (seq, x_seq), (bat, x_bat) = found[False], found[True]
    torch.testing.assert_close(x_bat, x_seq, rtol=1e-12, atol=1e-12)
    assert bat.run_values == pytest.approx(seq.run_values, rel=1e-12)
    assert bat.evaluations == seq.evaluations == 60 and bat.rollouts == 20


def test_batched_search_is_reproducible():
    results = []
    for _ in range(2):
        policy = BowlPolicy([0.0, 0.0])
        result = LBFGSSearch(max_iter=8, restarts=3, batched=True)(
            policy, lambda p=policy: p.value(), generator=torch.Generator().manual_seed(4))
        results.append((result, policy.x.detach().clone()))
    assert results[0][0] == results[1][0] and torch.equal(results[0][1], results[1][1])


def test_batched_search_needs_a_policy_and_one_value_per_restart():
    point = Point([0.0, 0.0])
    with pytest.raises(TypeError, match="unbatched qtl Policy"):
        LBFGSSearch(restarts=2, batched=True)(point, lambda: bowl(point))
    policy = BowlPolicy([0.0, 0.0])
    with pytest.raises(ValueError, match="one predicted return per restart"):
        LBFGSSearch(restarts=2, batched=True)(policy, lambda: policy.value().sum())
    assert policy.batch_shape == () and policy.x.shape == (2,)  # put back after a failure too


@pytest.mark.parametrize(("option", "target"), [("lbfgs", LBFGSSearch), ("adam", AdamSearch)])
def test_config_chooses_batched_restarts(option, target):
    """``optimizer.batched`` is a typed key of both options, true unless set false."""
    assert instantiate(train_config(f"optimizer={option}").optimizer).batched is True
    search = instantiate(train_config(f"optimizer={option}", "optimizer.batched=false").optimizer)
    assert isinstance(search, target) and search.batched is False


# -- MC-PILCO's schedule: dropout, plateaus, keep="last" --------------------------------------------------

LR, LR_MIN = 0.01, 0.0025
# The schedule's values at its three stages: Adam's learning rate and the policy dropout.
STAGES = [(0.01, 0.25), (0.005, 0.125), (0.0025, 0.0)]


def tiny_network() -> RBFNetwork:
    """A 3-basis RBF network on 2-D features, one action: a policy that can drop its basis functions."""
    gen = torch.Generator().manual_seed(0)
    return RBFNetwork(torch.randn(3, 2, generator=gen, dtype=torch.float64),
                      torch.randn(3, 1, generator=gen, dtype=torch.float64), torch.ones(1, 2, dtype=torch.float64))


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


def scheduled_search(**kwargs) -> AdamSearch:
    """MC-PILCO's schedule (lr 0.01 → 0.005 → 0.0025, dropout 0.25 → 0.125 → 0) with a short plateau rule."""
    settings = {"steps": 1000, "lr": LR, "keep": "last", "dropout": 0.25, "dropout_reduction": 0.125,
                "plateau": PlateauRule(ema=0.95, threshold=0.08, window=20, min_steps=20), "lr_reduction": 0.5,
                "lr_min": LR_MIN, **kwargs}
    return AdamSearch(**settings)


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
    result = AdamSearch(steps=12, lr=LR, dropout=0.3)(policy, objective)
    assert objective.dropouts == [0.3] * 12 and policy.dropout == 0.0 and result.evaluations == 12


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
    result = AdamSearch(steps=50, lr=0.05, keep="last")(point, objective)
    assert result.evaluations == len(objective.values) == 51  # every step, and one more at the final ψ
    assert torch.equal(point.x.detach(), objective.points[-1])  # the final ψ ...
    assert not torch.equal(objective.points[-1], objective.points[-2])  # ... after the last step
    assert result.value == objective.values[-1] == pytest.approx(float(bowl(point).detach()))  # ... its fresh value
    assert result.value < max(objective.values) and result.run_values == [result.value]


def test_keep_best_leaves_the_best_value_seen():
    point = Point([0.0, 0.0])
    objective = SpikedBowl(point)
    result = AdamSearch(steps=50, lr=0.05)(point, objective)
    assert result.evaluations == len(objective.values) == 50
    assert result.value == max(objective.values) == objective.values[2]  # the spike
    assert torch.equal(point.x.detach(), objective.points[2])


def test_keep_last_with_sequential_restarts_keeps_the_best_final_value():
    point = Point([0.0, 0.0])
    objective = SpikedBowl(point, spike_at=2)
    result = AdamSearch(steps=20, lr=0.05, restarts=2, perturbation=0.5, keep="last", batched=False)(
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


def test_keep_validated_leaves_the_best_snapshot_valued_afresh():
    """100 steps of 0.02 take x from 0 to 2; snapshots every 5 steps; the one at x = 1 (step 50) is kept."""
    point = Point([0.0, 0.0])
    objective = RiseAndFall(point)
    result = AdamSearch(steps=100, lr=0.02, keep="validated")(point, objective)
    assert result.evaluations == len(objective.points) == 100 + 21  # every step; the start, 19 snapshots, the final ψ
    assert float(point.x[0]) == pytest.approx(1.0, abs=1e-6) and result.value == pytest.approx(0.0, abs=1e-10)
    last = AdamSearch(steps=100, lr=0.02, keep="last")(Point([0.0, 0.0]), RiseAndFall(Point([0.0, 0.0])))
    assert last.value < -0.9  # keep="last" leaves x ≈ 2, where the value is ≈ −1


def test_keep_validated_passes_over_a_snapshot_that_fails():
    point = Point([0.0, 0.0])
    health.take()
    result = AdamSearch(steps=100, lr=0.02, keep="validated")(point, RiseAndFall(point, fail_above=1.5))
    counts = health.take()
    # The run stops at its first NaN (x > 1.5, step 76); its snapshots (steps 5-75) are valued and x = 1 is kept.
    assert float(point.x[0]) == pytest.approx(1.0, abs=1e-6) and result.value == pytest.approx(0.0, abs=1e-10)
    assert counts[health.SEARCH_STOPPED] == 1 and counts[health.NONFINITE] == 1


def test_keep_validated_never_leaves_a_worse_psi_than_its_start():
    """Started at the peak (x = 1), every step makes the value worse: the start, valued afresh, is kept."""
    point = Point([1.0, 0.0])
    result = AdamSearch(steps=40, lr=0.02, keep="validated")(point, RiseAndFall(point))
    assert float(point.x[0]) == 1.0 and result.value == 0.0


def test_config_keeps_validated():
    search = instantiate(train_config("optimizer=adam", "optimizer.keep=validated").optimizer)
    assert isinstance(search, AdamSearch) and search.keep == "validated" and search.batched is False


def test_a_dropout_search_is_reproducible_from_its_generator():
    """The masks come from the search's generator: the same seed, the same ψ; another seed, another ψ."""
    features = torch.randn(30, 2, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    target = features[:, :1].sin()

    def search(seed: int) -> torch.Tensor:
        policy = tiny_network()
        AdamSearch(steps=15, lr=0.05, dropout=0.25, keep="last")(
            policy, lambda: -(policy(features) - target).square().mean(), generator=torch.Generator().manual_seed(seed))
        return torch.cat([p.detach().flatten() for p in policy.parameters()])

    first = search(0)
    assert torch.equal(first, search(0))
    assert not torch.equal(first, search(1))


def test_scheduled_settings_refuse_batched_restarts():
    for settings in ({"dropout": 0.25}, {"keep": "last"}, {"plateau": PlateauRule()}):
        with pytest.raises(ValueError, match="restarts one after the other"):
            AdamSearch(restarts=2, batched=True, **settings)
        assert AdamSearch(restarts=1, batched=True, **settings).batched is False  # one restart: run sequentially
        assert AdamSearch(restarts=2, batched=False, **settings).restarts == 2


@pytest.mark.parametrize(("settings", "message"), [
    ({"keep": "first"}, "keep must be one of best, last"),
    ({"dropout": 1.0}, r"dropout must be in \[0, 1\)"),
    ({"dropout": -0.1}, r"dropout must be in \[0, 1\)"),
    ({"dropout_reduction": -0.1}, "dropout_reduction >= 0"),
    ({"lr_min": 0.02}, r"lr_min in \[0, lr\]"),
    ({"lr_min": -1e-3}, r"lr_min in \[0, lr\]"),
    ({"lr_reduction": 0.0}, r"lr_reduction must be in \(0, 1\]"),
    ({"lr_reduction": 1.5}, r"lr_reduction must be in \(0, 1\]"),
])
def test_bad_schedule_settings_are_named(settings, message):
    with pytest.raises(ValueError, match=message):
        AdamSearch(lr=0.01, **settings)


def test_a_plateau_rule_given_as_hydra_passes_it():
    """``optimizer.plateau`` of recipe=mc_pilco reaches AdamSearch as a DictConfig and becomes a PlateauRule."""
    search = instantiate(train_config("recipe=mc_pilco").optimizer)
    assert isinstance(search, AdamSearch) and search.plateau == PlateauRule(0.99, 0.08, 200, 200)
    assert (search.keep, search.dropout, search.lr, search.lr_min, search.batched) == ("validated", 0.25, 0.01, 0.0025,
                                                                                       False)
    plain = AdamSearch(plateau={"ema": 0.9, "threshold": 0.05, "window": 3, "min_steps": 1})
    assert plain.plateau == PlateauRule(0.9, 0.05, 3, 1)
    with pytest.raises(TypeError):
        AdamSearch(plateau={"windw": 3})


# -- per-parameter learning rates ------------------------------------------------------------------


def test_lr_scales_set_each_parameters_step_through_the_whole_schedule():
    """``lr_scales={"centres": 0.1}``: every Adam step moves the centres by 0.1 × the weights' step, at every stage."""
    policy = tiny_network()
    centres = []

    noise = torch.randn(5000, generator=torch.Generator().manual_seed(1), dtype=torch.float64)

    def objective() -> torch.Tensor:  # a constant gradient under flat noise: Adam steps by its lr, plateaus come
        centres.append(policy.centres.detach().clone())
        return 0.1 * (policy.weights.sum() + policy.centres.sum()) + noise[len(centres)]

    scheduled_search(lr_scales={"centres": 0.1})(policy, objective, generator=torch.Generator().manual_seed(0))
    steps = [float((b - a)[0, 0]) for a, b in itertools.pairwise(centres)]
    assert steps[0] == pytest.approx(0.1 * LR, rel=1e-4)
    assert sorted({round(s / 0.1, 6) for s in steps}, reverse=True) == [lr for lr, _ in STAGES]  # halved, scaled


@pytest.mark.parametrize("batched", [False, True])
def test_lr_scales_apply_to_batched_and_sequential_restarts(batched):
    """Two steps of 0.05 × 0.2: the best ψ seen is the second (after one step of ±0.01)."""
    policy = BowlPolicy([0.0, 0.0])
    AdamSearch(steps=2, lr=0.05, restarts=2, perturbation=0.0, batched=batched, lr_scales={"x": 0.2})(
        policy, policy.value)
    torch.testing.assert_close(policy.x.detach(), torch.tensor([0.01, -0.01], dtype=torch.float64))


def test_lr_scales_naming_no_parameter_are_refused():
    policy = tiny_network()
    with pytest.raises(ValueError, match=r"lr_scales names \['support_points'\].*choose from \['centres', "):
        AdamSearch(steps=1, lr_scales={"support_points": 0.1})(policy, lambda: policy.weights.sum())
    with pytest.raises(ValueError, match="lr_scales must be > 0"):
        AdamSearch(lr_scales={"centres": 0.0})


def test_config_lr_scales_are_checked_against_the_policy_at_build():
    """``optimizer.lr_scales`` reaches AdamSearch; a name the policy lacks is a UserError before any episode."""
    for override in ("+optimizer.lr_scales.support_points=0.05", "++optimizer.lr_scales={support_points:0.05}"):
        assert build(train_config("optimizer=adam", override)).search.lr_scales == {"support_points": 0.05}
    with pytest.raises(UserError, match=r"lr_scales names \['centres'\], which this policy does not have"):
        build(train_config("optimizer=adam", "+optimizer.lr_scales.centres=0.1"))
