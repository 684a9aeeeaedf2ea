"""Adam: batched restarts follow their own paths, a dropped restart leaves the others' moments; per-parameter lr."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from tests.policy_search.problems import LR, STAGES, BowlPolicy, adam, scheduled_search, tiny_network


def test_batched_adam_follows_each_restarts_own_path():
    """Adam acts per element: the batched search ends where the sequential one ends (round-off apart)."""
    found = {}
    for batched in (False, True):
        policy = BowlPolicy([0.0, 0.0])
        search = adam(steps=20, lr=0.05, restarts=3, perturbation=0.5, batched=batched)
        result = search(policy, policy.value, generator=torch.Generator().manual_seed(0))
        found[batched] = (result, policy.x.detach().clone())
    (seq, x_seq), (bat, x_bat) = found[False], found[True]
    torch.testing.assert_close(x_bat, x_seq, rtol=1e-12, atol=1e-12)
    assert bat.run_values == pytest.approx(seq.run_values, rel=1e-12)
    assert bat.evaluations == seq.evaluations == 60 and bat.rollouts == 20


def test_a_dropped_restart_leaves_the_others_on_their_own_paths():
    """Restart 1's 3rd value is NaN: it is dropped, and the others take the same step again, their moments kept.

    So each of the others ends where it ends alone, and the restart dropped keeps its best ψ, as a run that stops.
    """
    found = {}
    for batched in (False, True):
        policy = BowlPolicy([0.0, 0.0])
        search = adam(steps=20, lr=0.05, restarts=3, perturbation=0.5, batched=batched)
        bad_tag = float(search.starting_states(policy, torch.Generator().manual_seed(0))[1]["tag"])
        bad_calls = 0

        def objective(policy: BowlPolicy = policy, bad_tag: float = bad_tag) -> torch.Tensor:
            nonlocal bad_calls
            value = policy.value()
            hit = (policy.tag == bad_tag).flatten(start_dim=len(policy.batch_shape)).any(-1)
            bad_calls += int(hit.any())
            return torch.where(hit, math.nan, value) if bad_calls == 3 and bool(hit.any()) else value

        result = search(policy, objective, generator=torch.Generator().manual_seed(0))
        found[batched] = result
    seq, bat = found[False], found[True]
    assert seq.run_evaluations == [20, 3, 20]
    assert bat.run_evaluations == [21, 3, 21] and bat.rollouts == 21  # the step of the drop, taken again
    assert bat.run_values == pytest.approx(seq.run_values, rel=1e-12)
    assert bat.value == pytest.approx(seq.value, rel=1e-12)


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
    adam(steps=2, lr=0.05, restarts=2, perturbation=0.0, batched=batched, lr_scales={"x": 0.2})(
        policy, policy.value)
    torch.testing.assert_close(policy.x.detach(), torch.tensor([0.01, -0.01], dtype=torch.float64))


def test_lr_scales_naming_no_parameter_are_refused():
    policy = tiny_network()
    with pytest.raises(ValueError, match=r"lr_scales names \['support_points'\].*choose from \['centres', "):
        adam(steps=1, lr_scales={"support_points": 0.1})(policy, lambda: policy.weights.sum())
