"""The restart batch: ψ stacked in the policy; an evaluation names the restarts that fail, and they can be dropped."""

from __future__ import annotations

import math

import torch

from qtl import health
from qtl.policy_search.batch import RestartBatch
from tests.policy_search.problems import BowlPolicy, lbfgs


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
