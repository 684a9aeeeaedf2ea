"""Restarts: runs from the current ψ and from perturbations of it, one after the other or batched; the best ψ kept."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import ClassVar

import torch
from torch import Tensor, nn

from qtl import health
from qtl.errors import NonFiniteObjective
from qtl.policies import Policy
from qtl.policy_search.batch import RestartBatch
from qtl.policy_search.evaluation import INVALID_PSI_ERRORS, checked, count_failure, state
from qtl.policy_search.keep import first_snapshots, kept_afresh
from qtl.policy_search.result import SearchResult
from qtl.policy_search.settings import RestartSettings

log = logging.getLogger(__name__)

# Parameters with a spread below this are perturbed on this scale instead.
MIN_PERTURBATION_SCALE = 1e-3


def perturb(policy: nn.Module, scale: float, generator: torch.Generator | None) -> None:
    """ψ ← ψ + scale · spread(ψ) · ε, ε ~ N(0, I), per parameter tensor."""
    with torch.no_grad():
        for p in policy.parameters():
            spread = p.std() if p.numel() > 1 else p.abs().squeeze()
            spread = max(float(spread), MIN_PERTURBATION_SCALE)
            noise = torch.randn(p.shape, generator=generator, dtype=p.dtype).to(p.device)
            p.add_(scale * spread * noise)


class BestSeen:
    """The best ψ an objective has been evaluated at, and its value."""

    def __init__(self, policy: nn.Module) -> None:
        self.policy = policy
        self.value = -math.inf
        self.state: dict[str, Tensor] | None = None
        self.calls = 0  # evaluations of the objective, failed ones included

    def offer(self, value: float) -> None:
        """Keep the policy's current ψ if ``value`` is the best so far."""
        if value > self.value:
            self.value = value
            self.state = state(self.policy)


class RestartingSearch:
    """Runs from the current ψ and from ``restarts − 1`` perturbations of it; keeps the best ψ seen.

    An evaluation whose predicted return (or its gradient) is not finite, or whose propagation
    breaks down numerically, ends its run: the run keeps the best ψ it evaluated before.
    """

    settings_type: ClassVar[type[RestartSettings]] = RestartSettings  # what the constructor takes

    def __init__(self, settings: RestartSettings) -> None:
        self.settings = settings

    @property
    def restarts(self) -> int:
        """Runs in all, the first from the current ψ."""
        return self.settings.restarts

    @property
    def perturbation(self) -> float:
        """The scale of the later runs' perturbations of ψ (times each parameter's spread)."""
        return self.settings.perturbation

    @property
    def batched(self) -> bool:
        """Whether the restarts run all at once, ψ stacked in one rollout (else one after the other)."""
        return self.settings.batched

    @property
    def keep(self) -> str:
        """Which ψ a run leaves (one of :data:`~qtl.policy_search.keep.KEEP`): the best it evaluated."""
        return "best"

    def _run(self, policy: nn.Module, params: list[nn.Parameter], objective: Callable[[], Tensor],
             tick: Callable[[], None], generator: torch.Generator | None, snapshots: list[dict[str, Tensor]]) -> None:
        """A run from the ψ in ``policy``; with ``keep="validated"`` it appends snapshots of ψ to ``snapshots``."""
        raise NotImplementedError

    def _run_batched(self, batch: RestartBatch, objective: Callable[[], Tensor], tick: Callable[[], None]) -> None:
        """All runs at once on ``batch``, until every restart has stopped or left it."""
        raise NotImplementedError

    def starting_states(
        self, policy: nn.Module, generator: torch.Generator | None = None
    ) -> list[dict[str, Tensor]]:
        """Every restart's starting ψ: the current one, then perturbations drawn in the sequential search's order."""
        start = state(policy)
        states = [start]
        for _ in range(1, self.restarts):
            policy.load_state_dict(start)
            perturb(policy, self.perturbation, generator)
            states.append(state(policy))
        policy.load_state_dict(start)
        return states

    def __call__(
        self,
        policy: nn.Module,
        objective: Callable[[], Tensor],
        *,
        generator: torch.Generator | None = None,
        tick: Callable[[], None] = lambda: None,
    ) -> SearchResult:
        """Maximise ``objective()`` (a scalar of ψ = ``policy.parameters()``); leave the best ψ in ``policy``.

        Batched (``batched``): ``policy`` must be a :class:`~qtl.policies.Policy`, and
        ``objective()`` one value per restart `R` while its ψ are stacked `R x ...` (a propagator
        built on ``policy`` does this); ``tick`` is called once per batched evaluation.
        """
        if self.batched:
            return self._search_batched(policy, objective, generator, tick)
        start = state(policy)
        best = BestSeen(policy)
        run_values, run_evaluations = [], []
        for run in range(self.restarts):
            policy.load_state_dict(start)
            if run > 0:
                perturb(policy, self.perturbation, generator)
            seen = BestSeen(policy)

            def tracked(seen: BestSeen = seen) -> Tensor:
                seen.calls += 1
                value = checked(objective())
                seen.offer(float(value.detach()))
                return value

            params = [p for p in policy.parameters() if p.requires_grad]
            snapshots = first_snapshots(self.keep, policy)  # the run's start is one
            candidates: list[dict[str, Tensor]] = []
            try:
                self._run(policy, params, tracked, tick, generator, snapshots)
                candidates = [*snapshots, state(policy)]
            except INVALID_PSI_ERRORS as err:
                count_failure(err)
                health.count(health.SEARCH_STOPPED)
                candidates = snapshots  # taken before the invalid ψ; without any, the best ψ evaluated
                log.info("policy search run %d stopped at a numerically invalid ψ (%s); it keeps the best ψ %s",
                            run, err, "of its snapshots" if candidates else "it evaluated")
            kept = kept_afresh(self.keep, policy, objective, candidates, run)  # valued afresh (no dropout now)
            if kept is not None:
                seen.value, seen.state, calls = kept
                seen.calls += calls
            run_values.append(seen.value)
            run_evaluations.append(seen.calls)
            if seen.state is not None and seen.value > best.value:
                best.value, best.state = seen.value, seen.state
        if best.state is None:
            raise NonFiniteObjective("no policy search run evaluated a finite predicted return")
        policy.load_state_dict(best.state)
        return SearchResult(value=best.value, evaluations=sum(run_evaluations), run_values=run_values,
                            rollouts=sum(run_evaluations), run_evaluations=run_evaluations)

    def _search_batched(
        self,
        policy: nn.Module,
        objective: Callable[[], Tensor],
        generator: torch.Generator | None,
        tick: Callable[[], None],
    ) -> SearchResult:
        """All restarts at once, ψ stacked `R x ...`, rollouts batched; the best restart's best ψ left in ``policy``."""
        if not isinstance(policy, Policy) or policy.batch_shape:
            raise TypeError(f"a batched policy search needs an unbatched qtl Policy, got {type(policy).__name__}")
        states = self.starting_states(policy, generator)
        batch = RestartBatch(policy, states)
        try:
            self._run_batched(batch, objective, tick)
        finally:
            batch.close()
        best = max(range(self.restarts), key=lambda r: batch.best_value[r])
        if batch.best_psi[best] is None:
            raise NonFiniteObjective("no policy search run evaluated a finite predicted return")
        policy.load_state_dict({**states[0], **batch.best_psi[best]})
        return SearchResult(value=batch.best_value[best], evaluations=sum(batch.calls), run_values=batch.best_value,
                            rollouts=batch.rollouts, run_evaluations=batch.calls)
