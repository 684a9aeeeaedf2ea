"""Restarts: the search finds the maximum, keeps the best ψ across runs, survives invalid ψ; batched or one by one."""

from __future__ import annotations

import math

import pytest
import torch

from qtl import health
from qtl.errors import NonFiniteObjective
from tests.policy_search.problems import BowlPolicy, Point, adam, bowl, lbfgs, moment_matching_problem


@pytest.mark.parametrize("search", [lbfgs(max_iter=50, restarts=2), adam(steps=400, lr=0.05)])
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

    result = lbfgs(max_iter=50, restarts=1)(point, objective)
    assert math.isfinite(result.value) and point.x[0] <= 0.5
    assert result.evaluations >= 2  # the failed evaluation counts too
    assert result.value == pytest.approx(float(bowl(point)))


def test_nan_everywhere_is_reported():
    point = Point([0.0, 0.0])
    health.take()
    with pytest.raises(NonFiniteObjective, match="no policy search run"):
        lbfgs(max_iter=5, restarts=2)(point, lambda: point.x.sum() * math.nan)
    counts = health.take()  # each run's first evaluation is NaN: it stops there
    assert counts[health.NONFINITE] == 2 and counts[health.SEARCH_STOPPED] == 2 and counts[health.LINALG] == 0


def test_a_failed_factorisation_is_counted_apart_from_a_nan():
    point = Point([0.0, 0.0])

    def objective() -> torch.Tensor:
        raise torch.linalg.LinAlgError("not positive-definite")

    health.take()
    with pytest.raises(NonFiniteObjective, match="no policy search run"):
        adam(steps=5, restarts=3)(point, objective)
    assert health.take() == {**dict.fromkeys(health.EVENTS, 0), health.LINALG: 3, health.SEARCH_STOPPED: 3}


# -- batched restarts ---------------------------------------------------------------------------------


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


@pytest.mark.parametrize("make", [lambda b: lbfgs(max_iter=5, restarts=3, perturbation=0.5, batched=b),
                                  lambda b: adam(steps=5, restarts=3, perturbation=0.5, batched=b)])
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


@pytest.mark.parametrize("search", [lbfgs(max_iter=30, restarts=3, batched=True),
                                    adam(steps=300, lr=0.05, restarts=3, batched=True)])
def test_batched_search_finds_the_maximum_and_leaves_the_best_restart(search):
    policy = BowlPolicy([0.0, 0.0])
    result = search(policy, policy.value, generator=torch.Generator().manual_seed(0))
    assert policy.batch_shape == () and policy.x.shape == (2,)  # the plain policy again
    assert result.value == pytest.approx(1.0, abs=1e-4) and result.value == max(result.run_values)
    assert result.value == pytest.approx(float(policy.value()), abs=0, rel=0)  # the best ψ is the one left
    assert len(result.run_values) == 3 and result.evaluations == sum(result.run_evaluations)
    assert result.rollouts == max(result.run_evaluations)  # one batched rollout per round, restarts in lockstep


def test_batched_search_of_a_real_rollout_improves_it(gp_factory):
    """Moment matching, squashed RBF policy: the batched search improves V and leaves the best restart's ψ."""
    policy, objective = moment_matching_problem(gp_factory)
    with torch.no_grad():
        before = float(objective())
    ticks = []
    result = lbfgs(max_iter=4, restarts=2, batched=True)(
        policy, objective, generator=torch.Generator().manual_seed(1), tick=lambda: ticks.append(1))
    with torch.no_grad():
        after = float(objective())
    assert result.value > before and result.value == max(result.run_values)
    assert after == pytest.approx(result.value, rel=1e-12, abs=0)  # batched and plain rollouts: round-off apart
    assert result.rollouts == len(ticks) <= 4 and result.evaluations == 2 * result.rollouts


@pytest.mark.parametrize("failure", ["nan", "linalg"])
@pytest.mark.parametrize("make", [lambda: lbfgs(max_iter=40, restarts=3, perturbation=0.5, batched=True),
                                  lambda: adam(steps=200, lr=0.05, restarts=3, perturbation=0.5, batched=True)])
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


def test_batched_search_is_reproducible():
    results = []
    for _ in range(2):
        policy = BowlPolicy([0.0, 0.0])
        result = lbfgs(max_iter=8, restarts=3, batched=True)(
            policy, lambda p=policy: p.value(), generator=torch.Generator().manual_seed(4))
        results.append((result, policy.x.detach().clone()))
    assert results[0][0] == results[1][0] and torch.equal(results[0][1], results[1][1])


def test_batched_search_needs_a_policy_and_one_value_per_restart():
    point = Point([0.0, 0.0])
    with pytest.raises(TypeError, match="unbatched qtl Policy"):
        lbfgs(restarts=2, batched=True)(point, lambda: bowl(point))
    policy = BowlPolicy([0.0, 0.0])
    with pytest.raises(ValueError, match="one predicted return per restart"):
        lbfgs(restarts=2, batched=True)(policy, lambda: policy.value().sum())
    assert policy.batch_shape == () and policy.x.shape == (2,)  # put back after a failure too
