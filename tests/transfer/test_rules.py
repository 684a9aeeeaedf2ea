"""Updating rules on hand-computed values: forgetting (Eq. 6-7), Bayesian (Eq. 8-12), none, free."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from qtl.errors import RuleError
from qtl.models import GPHyperparameters
from qtl.transfer import Bayesian, Forgetting, Free, NoTransfer
from qtl.transfer.rules import from_space, to_space


def theta(values: list[list[float]]) -> GPHyperparameters:
    """θ from its natural `E x (D + 2)` rows."""
    return GPHyperparameters.from_natural(torch.tensor(values, dtype=torch.float64))


THETA_S = theta([[1.0, 4.0, 0.5, 1e-3], [2.0, 8.0, 2.0, 1e-4]])  # E = 2, D = 2
THETA_P = theta([[3.0, 1.0, 0.25, 1e-2], [0.5, 2.0, 1.0, 1e-6]])
THETA_P2 = theta([[2.0, 2.0, 1.0, 4e-3], [1.0, 4.0, 4.0, 1e-5]])


def natural(t: GPHyperparameters) -> torch.Tensor:
    return t.natural()


def test_forgetting_natural_space_is_eq7_exactly():
    rule = Forgetting(gamma=0.9, space="natural")
    assert rule.start(THETA_S) is THETA_S  # Eq. 6
    first = rule.update(THETA_S, THETA_P, 100)
    expected = 0.9 * natural(THETA_S) + 0.1 * natural(THETA_P)  # Eq. 7 by hand
    torch.testing.assert_close(natural(first), expected, rtol=0, atol=1e-15)
    assert natural(first)[0, 0].item() == pytest.approx(0.9 * 1.0 + 0.1 * 3.0, abs=1e-15)
    second = rule.update(first, THETA_P2, 150)
    torch.testing.assert_close(natural(second), 0.9 * expected + 0.1 * natural(THETA_P2), rtol=0, atol=1e-15)


def test_forgetting_log_space_is_a_weighted_geometric_mean():
    rule = Forgetting(gamma=0.5, space="log")
    blended = rule.update(THETA_S, THETA_P, 100)
    torch.testing.assert_close(natural(blended), (natural(THETA_S) * natural(THETA_P)).sqrt(), rtol=1e-13, atol=0)
    assert natural(blended)[0, 0].item() == pytest.approx(math.sqrt(3.0), rel=1e-13)


@pytest.mark.parametrize("space", ["log", "natural"])
def test_gamma_zero_gives_theta_p_and_gamma_one_keeps_theta_s(space):
    zero, one = Forgetting(gamma=0.0, space=space), Forgetting(gamma=1.0, space=space)
    kept = one.start(THETA_S)
    for learned in (THETA_P, THETA_P2):
        assert torch.equal(natural(zero.update(THETA_S, learned, 100)), natural(learned))
        kept = one.update(kept, learned, 100)
    assert torch.equal(natural(kept), natural(THETA_S))


@pytest.mark.parametrize("gamma", [-0.1, 1.5, float("nan")])
def test_gamma_outside_unit_interval_is_refused(gamma):
    with pytest.raises(RuleError, match=r"rule.gamma must be in \[0, 1\]"):
        Forgetting(gamma=gamma)


def test_unknown_space_is_refused():
    with pytest.raises(RuleError, match=r"rule\.space must be one of"):
        Forgetting(gamma=0.5, space="sqrt")


def test_bayesian_matches_eq10_eq11_by_hand():
    rule = Bayesian(source_variance=1.0, evidence_variance=100.0, space="natural")
    prior = rule.start(THETA_S)
    # n = 50: σ_p² = 2 (Eq. 12), σ_1² = 2·1/(2+1) = 2/3 (Eq. 10), μ_1 = (2/3)(θ_s/1 + θ_p/2) (Eq. 11).
    first = rule.update(prior, THETA_P, 50)
    torch.testing.assert_close(natural(first), (2 * natural(THETA_S) + natural(THETA_P)) / 3, rtol=1e-14, atol=0)
    assert rule.variance == pytest.approx(2.0 / 3.0, rel=1e-15)
    # n = 100: σ_p² = 1, σ_2² = (2/3)/(5/3) = 0.4, μ_2 = 0.4(μ_1/(2/3) + θ_p2) = 0.6 μ_1 + 0.4 θ_p2.
    second = rule.update(first, THETA_P2, 100)
    torch.testing.assert_close(natural(second), 0.6 * natural(first) + 0.4 * natural(THETA_P2), rtol=1e-14, atol=0)
    assert rule.variance == pytest.approx(0.4, rel=1e-15)
    assert natural(first)[0, 0].item() == pytest.approx((2 * 1.0 + 3.0) / 3, rel=1e-15)


def test_bayesian_log_space_fuses_log_values():
    rule = Bayesian(source_variance=1.0, evidence_variance=100.0, space="log")
    fused = rule.update(rule.start(THETA_S), THETA_P, 100)  # σ_p² = σ_0² = 1: equal weights
    torch.testing.assert_close(fused.log(), (THETA_S.log() + THETA_P.log()) / 2, rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("space", ["log", "natural"])
def test_bayesian_approaches_theta_p_as_n_grows(space):
    gaps = []
    for n in (10, 1_000, 100_000, 10_000_000):
        rule = Bayesian(space=space)
        fused = rule.update(rule.start(THETA_S), THETA_P, n)
        gaps.append(float(((to_space(fused, space) - to_space(THETA_P, space)).abs()).max()))
    assert all(b < a for a, b in itertools.pairwise(gaps))
    assert gaps[-1] < 1e-4 * max(gaps[0], 1.0)


def test_bayesian_state_round_trips_and_start_resets_it():
    rule = Bayesian()
    rule.update(rule.start(THETA_S), THETA_P, 50)
    state = rule.state_dict()
    other = Bayesian()
    other.load_state_dict(state)
    assert other.variance == rule.variance < rule.source_variance
    resumed, original = other.update(THETA_S, THETA_P2, 80), rule.update(THETA_S, THETA_P2, 80)
    torch.testing.assert_close(natural(resumed), natural(original))
    rule.start(THETA_S)
    assert rule.variance == rule.source_variance


@pytest.mark.parametrize("kwargs", [{"source_variance": 0.0}, {"evidence_variance": -1.0}])
def test_bayesian_refuses_nonpositive_variances(kwargs):
    with pytest.raises(RuleError, match="must be > 0"):
        Bayesian(**kwargs)


def test_none_and_free_follow_theta_p():
    assert NoTransfer().update(THETA_S, THETA_P, 10) is THETA_P
    assert not NoTransfer.uses_source and not NoTransfer.warm_start
    free = Free()
    assert free.start(THETA_S) is THETA_S
    assert free.update(THETA_S, THETA_P, 10) is THETA_P
    assert Free.uses_source and Free.warm_start


@pytest.mark.parametrize("space", ["log", "natural"])
def test_spaces_round_trip(space):
    torch.testing.assert_close(natural(from_space(to_space(THETA_S, space), space)), natural(THETA_S))
