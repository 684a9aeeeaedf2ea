"""The restart batch: ψ stacked in the policy; an evaluation names the restarts that fail, and they can be dropped."""

from __future__ import annotations

import math

import pytest
import torch

from qtl import health
from qtl.lbfgs import INVALID
from qtl.policy_search.batch import RestartBatch
from tests.policy_search.problems import BowlPolicy, lbfgs
from tests.propagation.failing import BAD, ENGINES, HORIZON, restart_states, solo, system

# The good restarts of a batch against their rollouts alone: the same maths, another batch size.
SOLO_RTOL = 1e-10


def open_batch(restarts: int = 3) -> tuple[BowlPolicy, RestartBatch]:
    """The bowl policy with ``restarts`` perturbed restarts stacked in it."""
    policy = BowlPolicy([0.0, 0.0])
    states = lbfgs(restarts=restarts, perturbation=0.5).starting_states(policy, torch.Generator().manual_seed(0))
    return policy, RestartBatch(policy, states)


def test_an_evaluation_offers_each_finite_value_and_names_none_when_all_are():
    policy, batch = open_batch()
    values, failing = batch.evaluate(policy.value)
    assert failing == [] and values.shape == (3,) and batch.rollouts == 1 and batch.calls == [1, 1, 1]
    assert batch.best_value == values.detach().tolist()
    batch.close()
    assert policy.batch_shape == () and policy.x.shape == (2,)


def test_a_value_that_is_not_finite_names_its_restart_which_leaves_the_batch():
    policy, batch = open_batch()
    health.take()
    values, failing = batch.evaluate(lambda: torch.where(torch.arange(3) == 1, math.nan, policy.value()))
    assert failing == [1] and values is not None
    assert math.isfinite(batch.best_value[0]) and batch.best_value[1] == -math.inf  # the finite ones offered
    assert batch.drop(failing) == [0, 2] and batch.active == [0, 2] and policy.x.shape == (2, 2)
    assert health.take()[health.NONFINITE] == 1
    _, failing = batch.evaluate(policy.value)  # the others go on
    assert failing == [] and batch.calls == [2, 1, 2]
    batch.close()


def test_a_failed_rollout_names_the_restarts_that_fail_alone():
    """The batched rollout raises; each restart is evaluated alone: the one that raises alone is named."""
    policy, batch = open_batch()
    bad_tag = float(batch.start["tag"][2])

    def objective() -> torch.Tensor:
        if bool((policy.tag == bad_tag).any()):
            raise torch.linalg.LinAlgError("not positive-definite")
        return policy.value()

    health.take()
    values, failing = batch.evaluate(objective)
    assert values is None and failing == [2]
    assert batch.rollouts == 1 + 3 and batch.calls == [2, 2, 2]  # the batched rollout, then each restart alone
    assert health.take()[health.LINALG] == 2  # the batched rollout's failure and restart 2's own
    assert math.isfinite(batch.best_value[0]) and math.isfinite(batch.best_value[1])
    batch.close()


def test_gradients_that_are_not_finite_name_their_restarts():
    policy, batch = open_batch()
    values, _ = batch.evaluate(policy.value)
    (values * torch.tensor([1.0, math.inf, 1.0], dtype=values.dtype)).sum().backward()
    health.take()
    assert batch.nonfinite_gradients() == [1] and health.take()[health.NONFINITE] == 1
    for p in batch.trainable():
        p.grad = None
    policy.value().sum().backward()
    assert batch.nonfinite_gradients() == []
    batch.close()


@pytest.mark.parametrize("moments", ENGINES)
def test_a_restart_that_fails_a_factorisation_leaves_alone_the_others_batched(moments, monkeypatch):
    """One restart's covariance is not positive-definite: INVALID for it (one linalg failure counted), the others'
    answers those of their rollouts alone, and no restart is evaluated alone."""
    policy, propagator, start = system(moments)
    states = restart_states(policy)
    monkeypatch.setattr(RestartBatch, "_alone", lambda *_: pytest.fail("evaluated each restart alone"))
    batch = RestartBatch(policy, states)
    health.take()
    answers = batch.evaluate_each(lambda: propagator.expected_return(start, HORIZON))
    batch.close()
    counts = health.take()
    assert counts[health.LINALG] == 1 and counts[health.NONFINITE] == 0
    assert answers[BAD] is INVALID and batch.rollouts == 1 and batch.best_value[BAD] == -math.inf
    for position in (0, 2):
        value, grad = solo(policy, propagator, start, states[position])
        loss, minus_grad = answers[position]
        torch.testing.assert_close(loss, -float(value), rtol=SOLO_RTOL, atol=0)
        torch.testing.assert_close(-minus_grad, grad, rtol=SOLO_RTOL, atol=SOLO_RTOL * float(grad.abs().max()))


def test_a_restart_that_fails_a_factorisation_is_named_by_a_batched_evaluation(monkeypatch):
    """Adam's evaluation: the failing restart is named (a linalg failure), the others' values offered."""
    policy, propagator, start = system("fused")
    monkeypatch.setattr(RestartBatch, "_alone", lambda *_: pytest.fail("evaluated each restart alone"))
    batch = RestartBatch(policy, restart_states(policy))
    health.take()
    values, failing = batch.evaluate(lambda: propagator.expected_return(start, HORIZON))
    assert failing == [BAD] and values is not None and health.take()[health.LINALG] == 1
    assert batch.drop(failing) == [0, 2]
    values, failing = batch.evaluate(lambda: propagator.expected_return(start, HORIZON))  # the others go on
    assert failing == [] and values.shape == (2,) and health.take()[health.LINALG] == 0
    batch.close()
