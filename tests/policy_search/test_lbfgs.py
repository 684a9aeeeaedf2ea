"""Batched L-BFGS runs each restart's own L-BFGS in lockstep: per restart it is the sequential search."""

from __future__ import annotations

import math

import pytest
import torch

from qtl import health
from tests.policy_search.problems import (
    ValleyPolicy,
    invalid,
    lbfgs,
    moment_matching_problem,
    points_per_restart,
    trainable_psi,
)

# Points of a batched and a sequential L-BFGS run agree to this, relative to their norm (seen: ~1e-10).
POINT_RTOL = 1e-8


def test_batched_lbfgs_runs_each_restart_as_the_sequential_search(gp_factory):
    """Lockstep L-BFGS (moment matching): per restart the same points, evaluations and best V as torch's LBFGS alone."""
    runs = {}
    for batched in (False, True):
        policy, objective = moment_matching_problem(gp_factory)
        search = lbfgs(max_iter=12, restarts=3, perturbation=1.0, batched=batched)
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


def test_lbfgs_retreats_from_an_invalid_region_and_goes_on_alone_or_batched():
    """A restart whose line search steps into the invalid region retreats halfway back (again and again) and goes
    on to the maximum instead of stopping there; alone or batched, the same points."""
    results = {}
    for batched in (False, True):
        policy = ValleyPolicy([-1.0, 0.5])
        search = lbfgs(max_iter=30, restarts=4, perturbation=0.5, batched=batched)
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
    result = lbfgs(max_iter=10, restarts=1)(policy, objective)
    counts = health.take()
    assert counts[health.SEARCH_STOPPED] == 1 and counts[health.NONFINITE] >= 2
    assert result.value == pytest.approx(float(ValleyPolicy([0.55, 0.2]).value()))
    torch.testing.assert_close(policy.x.detach(), torch.tensor([0.55, 0.2], dtype=policy.x.dtype))

