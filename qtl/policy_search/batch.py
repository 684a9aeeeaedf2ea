"""The restarts of a batched search: their ψ stacked `R' x ...` in the policy, evaluated in one rollout each round.

A restart whose evaluation is not finite, or whose rollout fails alone, leaves the batch: the
evaluations name such restarts in what they return, and :meth:`RestartBatch.drop` removes them.
The batched rollout runs inside :func:`qtl.gaussian.element_failures`: a factorisation that fails for
one restart (a covariance not positive-definite) makes that restart's value NaN, and the others' values
and gradients are those they have without it; only what still raises re-evaluates each restart alone.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from typing import NamedTuple

import torch
from torch import Tensor, nn

from qtl import health
from qtl.gaussian import element_failures
from qtl.lbfgs import INVALID, Evaluation
from qtl.policies import Policy, psi_names, set_psi, stack_psi
from qtl.policy_search.evaluation import INVALID_PSI_ERRORS, count_failure

log = logging.getLogger(__name__)


class Values(NamedTuple):
    """V `R'` of the active restarts from one rollout, or the batch positions of the restarts that leave instead."""

    values: Tensor | None  # None where the batched rollout failed
    failing: list[int]  # positions whose value is not finite or whose own rollout fails: they are to be dropped


class RestartBatch:
    """The restarts still running, their ψ stacked `R' x ...` in the policy, and each restart's best ψ seen.

    While it is open, ``policy``'s parameters are the stacked ψ of the active restarts (so that
    ``objective()`` evaluates all of them in one rollout); :meth:`close` puts the plain ones back.
    A restart's trainable ψ flattened (parameters in ``named_parameters`` order, as
    ``torch.optim.LBFGS`` flattens them) is its point `n`.
    """

    def __init__(self, policy: Policy, states: list[dict[str, Tensor]]) -> None:
        self.policy = policy
        self.names = psi_names(policy)
        restarts = len(states)
        self.best_value = [-math.inf] * restarts
        self.best_psi: list[dict[str, Tensor] | None] = [None] * restarts
        self.calls = [0] * restarts  # evaluations per restart, failed ones included
        self.rollouts = 0  # calls of the objective
        self.active = list(range(restarts))
        self.requires_grad = {name: p.requires_grad for name, p in policy.named_parameters()}
        self.start = stack_psi(states, self.names)  # `R x ...`: the parts of ψ no optimiser moves stay these
        self.segments: dict[str, slice] = {}  # where each trainable parameter lies in a point
        offset = 0
        for name in self.names:
            if self.requires_grad[name]:
                size = self.start[name][0].numel()
                self.segments[name], offset = slice(offset, offset + size), offset + size
        self.params: dict[str, nn.Parameter] = {}
        self.plain = set_psi(policy, self._stacked(self.start), (restarts,))

    def _stacked(self, psi: dict[str, Tensor]) -> dict[str, nn.Parameter]:
        """ψ `R' x ...` as the leaf parameters the optimiser moves; installed in the policy."""
        self.params = {name: nn.Parameter(value.clone(), requires_grad=self.requires_grad[name])
                       for name, value in psi.items()}
        return self.params

    def trainable_named(self) -> dict[str, nn.Parameter]:
        """The stacked parameters an optimiser moves (those of ψ that require gradients), by name."""
        return {name: p for name, p in self.params.items() if p.requires_grad}

    def trainable(self) -> list[nn.Parameter]:
        """The stacked parameters an optimiser moves, in ``named_parameters`` order."""
        return list(self.trainable_named().values())

    def point(self, position: int) -> Tensor:
        """The trainable ψ of the restart at ``position``, flattened: `n`."""
        return torch.cat([p[position].detach().reshape(-1) for p in self.trainable()])

    def load(self, points: Mapping[int, Tensor]) -> None:
        """Make the restarts in ``points`` (restart → point `n`) the active ones, in that order, at those points."""
        self.active = list(points)
        stacked = torch.stack(list(points.values()))  # R' x n
        psi = {name: stacked[:, self.segments[name]].reshape(len(self.active), *self.start[name].shape[1:])
               if name in self.segments else self.start[name][self.active] for name in self.names}
        set_psi(self.policy, self._stacked(psi), (len(self.active),))

    def close(self) -> None:
        """Put the policy's plain parameters back (their values are those before the search)."""
        set_psi(self.policy, self.plain)

    def _psi_at(self, position: int) -> dict[str, Tensor]:
        """The current ψ of the restart at ``position`` in the batch, detached."""
        return {name: p[position].detach().clone() for name, p in self.params.items()}

    def _offer(self, position: int, value: float) -> None:
        restart = self.active[position]
        if value > self.best_value[restart]:
            self.best_value[restart] = value
            self.best_psi[restart] = self._psi_at(position)

    def _count_rollout(self, restarts: list[int]) -> None:
        """One rollout more, evaluating each of ``restarts`` once more."""
        self.rollouts += 1
        for restart in restarts:
            self.calls[restart] += 1

    def evaluate_each(self, objective: Callable[[], Tensor]) -> list[Evaluation]:
        """(−V_r, −∂V_r/∂ψ_r flattened `n`) of each active restart from one rollout; INVALID where either is not finite.

        Each finite value is offered as its restart's best. A restart whose factorisation failed has a NaN
        value (counted as a linalg failure). When the batched rollout still raises numerically, each restart
        is evaluated alone (as the sequential search would).
        """
        self._count_rollout(self.active)
        try:
            with element_failures() as failures:
                values = objective()
            self._check_shape(values)
            (-values.sum()).backward()
        except INVALID_PSI_ERRORS as err:
            count_failure(err)
            log.info("batched policy search: the rollout failed (%s); evaluating each restart alone", err)
            alone = self._alone(objective)
            return [self._answer(position, value, grad) for position, (value, grad) in enumerate(alone)]
        params = self.trainable()
        return [self._answer(position, values[position].detach(), flat_grad(params, position), bool(failures))
                for position in range(len(self.active))]

    def _answer(self, position: int, value: Tensor | None, grad: Tensor | None, linalg: bool = False) -> Evaluation:
        """The evaluation an optimiser receives for the restart at ``position``; a finite value is offered.

        ``linalg``: a factorisation failed in the rollout, so that a value that is not finite counts as a
        linalg failure.
        """
        if value is None or grad is None:  # failed alone: counted there
            return INVALID
        if not bool(torch.isfinite(value)):
            health.count(health.LINALG if linalg else health.NONFINITE)
            return INVALID
        self._offer(position, float(value))
        if not bool(torch.isfinite(grad).all()):
            health.count(health.NONFINITE)
            return INVALID
        return -float(value), grad

    def _check_shape(self, values: Tensor) -> None:
        if values.shape != (len(self.active),):
            raise ValueError(f"a batched policy search needs one predicted return per restart "
                             f"`{len(self.active)}`, the objective gave shape {tuple(values.shape)}")

    def evaluate(self, objective: Callable[[], Tensor]) -> Values:
        """V `R'` of the active restarts in one rollout, each finite value offered as its restart's best.

        Its ``failing`` names the restarts whose value is not finite (a failed factorisation makes it NaN,
        counted as a linalg failure), or, when the batched rollout still raises numerically, those that fail
        alone when re-evaluated one by one (``values`` None then).
        """
        self._count_rollout(self.active)
        try:
            with element_failures() as failures:
                values = objective()
        except INVALID_PSI_ERRORS as err:
            count_failure(err)
            log.info("batched policy search: the rollout failed (%s); re-evaluating each restart", err)
            return Values(None, self._failing_alone(objective))
        self._check_shape(values)
        finite = torch.isfinite(values.detach())
        for position in range(len(self.active)):
            if finite[position]:
                self._offer(position, float(values[position].detach()))
        if not finite.all():
            health.count(health.LINALG if failures else health.NONFINITE, int((~finite).sum()))
            return Values(values, (~finite).nonzero().flatten().tolist())
        return Values(values, [])

    def _alone(self, objective: Callable[[], Tensor]) -> list[tuple[Tensor | None, Tensor | None]]:
        """V and −∂V/∂ψ flattened `n` of each active restart evaluated alone, both None where that raises."""
        found: list[tuple[Tensor | None, Tensor | None]] = []
        try:
            for position, restart in enumerate(self.active):
                self._count_rollout([restart])
                single = {name: nn.Parameter(p[position : position + 1].detach().clone(),
                                             requires_grad=p.requires_grad) for name, p in self.params.items()}
                set_psi(self.policy, single, (1,))
                try:
                    value = objective()
                    (-value.sum()).backward()
                except INVALID_PSI_ERRORS as err:
                    count_failure(err)
                    found.append((None, None))
                    continue
                trainable = [p for p in single.values() if p.requires_grad]
                found.append((value.detach().sum(), flat_grad(trainable, 0)))
        finally:
            set_psi(self.policy, self.params, (len(self.active),))
        return found

    def _failing_alone(self, objective: Callable[[], Tensor]) -> list[int]:
        """Positions of the restarts whose own evaluation (value or gradient) fails; the others' values offered."""
        failing = []
        for position, (value, grad) in enumerate(self._alone(objective)):
            if value is not None and grad is not None and bool(torch.isfinite(value)) and bool(
                    torch.isfinite(grad).all()):
                self._offer(position, float(value))
            else:
                if value is not None and grad is not None:  # evaluated, not finite (a raise was counted in _alone)
                    health.count(health.NONFINITE)
                failing.append(position)
        if not failing:
            log.info("batched policy search: no restart fails alone; every restart stops at its best ψ")
            return list(range(len(self.active)))
        return failing

    def nonfinite_gradients(self) -> list[int]:
        """Positions of the restarts whose gradient is not finite (counted): they are to be dropped."""
        bad = torch.zeros(len(self.active), dtype=torch.bool)
        for p in self.trainable():
            if p.grad is not None:
                bad |= ~torch.isfinite(p.grad).reshape(len(self.active), -1).all(-1).cpu()
        if bad.any():
            health.count(health.NONFINITE, int(bad.sum()))
        return bad.nonzero().flatten().tolist()

    def drop(self, positions: list[int]) -> list[int]:
        """Remove the restarts at ``positions``; the others go on from their current ψ; the kept positions."""
        for position in positions:
            health.count(health.SEARCH_STOPPED)
            log.info("policy search restart %d stopped at a numerically invalid ψ; it keeps the best ψ it "
                        "evaluated", self.active[position])
        kept = [position for position in range(len(self.active)) if position not in set(positions)]
        states = [self._psi_at(position) for position in kept]
        self.active = [self.active[position] for position in kept]
        if self.active:
            set_psi(self.policy, self._stacked(stack_psi(states, self.names)), (len(self.active),))
        return kept


def flat_grad(params: list[nn.Parameter], position: int) -> Tensor:
    """The gradient of the restart at ``position`` of stacked ``params``, flattened `n` (zeros where there is none)."""
    return torch.cat([p.grad[position].reshape(-1) if p.grad is not None else p.new_zeros(p[position].numel())
                      for p in params])


