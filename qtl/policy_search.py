"""Policy improvement: maximise the predicted return V^π(ψ) by gradients (Algorithm 1, lines 6-9).

Restarts run one after the other, or (``batched=True``) all at once: their ψ stacked as a leading
restart dimension `R` of the policy (:mod:`qtl.policies.batching`), one batched rollout evaluates
all R predicted returns, and one optimiser maximises their sum Σ_r V_r over the concatenated ψ
(BoTorch's joint optimisation of restarts, ``gen_candidates_scipy``). The gradient of the sum is
block-separable, so each restart gets its own gradient. The batched search starts from the same
points as the sequential one; what differs: L-BFGS's curvature memory, line search and stopping
tests are joint (Adam acts per element, so its restarts follow their own paths), a batched value
equals the plain policy's to round-off (~1e-15 relative), and a stochastic objective (particles
with ``resample_every > 0``) advances its draws once per batched evaluation, shared by the restarts.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from qtl.errors import NonFiniteObjective
from qtl.policies import Policy, psi_names, set_psi, stack_psi

log = logging.getLogger(__name__)

# Parameters with a spread below this are perturbed on this scale instead.
MIN_PERTURBATION_SCALE = 1e-3
# Errors of an evaluation at a numerically invalid ψ: they end a run (sequential) or drop a restart (batched).
INVALID_PSI_ERRORS = (NonFiniteObjective, torch.linalg.LinAlgError)


@dataclass(frozen=True)
class SearchResult:
    """Outcome of a policy search: the best predicted return and what it cost.

    ``evaluations`` counts evaluations of one restart's predicted return, failed ones included: a
    batched rollout of R restarts counts R, so that sequential and batched searches compare.
    ``rollouts`` counts calls of the objective: equal to ``evaluations`` when sequential, one per
    batched rollout (plus the single-restart re-evaluations that locate a failure) when batched.
    """

    value: float
    evaluations: int
    run_values: list[float]  # best value of each run (-inf for a run that evaluated nothing finite)
    rollouts: int


def _perturb(policy: nn.Module, scale: float, generator: torch.Generator | None) -> None:
    """ψ ← ψ + scale · spread(ψ) · ε, ε ~ N(0, I), per parameter tensor."""
    with torch.no_grad():
        for p in policy.parameters():
            spread = p.std() if p.numel() > 1 else p.abs().squeeze()
            spread = max(float(spread), MIN_PERTURBATION_SCALE)
            noise = torch.randn(p.shape, generator=generator, dtype=p.dtype).to(p.device)
            p.add_(scale * spread * noise)


def _checked(value: Tensor) -> Tensor:
    if not torch.isfinite(value).all():
        raise NonFiniteObjective(f"predicted return is {value.item()}")
    return value


class _BestSeen:
    """The best ψ an objective has been evaluated at, and its value."""

    def __init__(self, policy: nn.Module) -> None:
        self.policy = policy
        self.value = -math.inf
        self.state: dict[str, Tensor] | None = None
        self.calls = 0  # evaluations of the objective, failed ones included

    def offer(self, value: float) -> None:
        if value > self.value:
            self.value = value
            self.state = {k: v.detach().clone() for k, v in self.policy.state_dict().items()}


class _RestartingSearch:
    """Runs from the current ψ and from ``restarts − 1`` perturbations of it; keeps the best ψ seen.

    An evaluation whose predicted return (or its gradient) is not finite, or whose propagation
    breaks down numerically, ends its run: the run keeps the best ψ it evaluated before.
    """

    def __init__(self, restarts: int, perturbation: float, batched: bool = False) -> None:
        if restarts < 1:
            raise ValueError(f"restarts must be >= 1, got {restarts}")
        if perturbation < 0:
            raise ValueError(f"perturbation must be >= 0, got {perturbation}")
        self.restarts = restarts
        self.perturbation = perturbation
        self.batched = bool(batched)

    def _run(self, params: list[nn.Parameter], objective: Callable[[], Tensor], tick: Callable[[], None]) -> None:
        raise NotImplementedError

    def _run_batched(self, batch: _RestartBatch, objective: Callable[[], Tensor], tick: Callable[[], None]) -> None:
        raise NotImplementedError

    def starting_states(
        self, policy: nn.Module, generator: torch.Generator | None = None
    ) -> list[dict[str, Tensor]]:
        """Every restart's starting ψ: the current one, then perturbations drawn in the sequential search's order."""
        start = {k: v.detach().clone() for k, v in policy.state_dict().items()}
        states = [start]
        for _ in range(1, self.restarts):
            policy.load_state_dict(start)
            _perturb(policy, self.perturbation, generator)
            states.append({k: v.detach().clone() for k, v in policy.state_dict().items()})
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

        Batched (``batched=True``): ``policy`` must be a :class:`~qtl.policies.Policy`, and
        ``objective()`` one value per restart `R` while its ψ are stacked `R x ...` (a propagator
        built on ``policy`` does this); ``tick`` is called once per batched evaluation.
        """
        if self.batched:
            return self._search_batched(policy, objective, generator, tick)
        start = {k: v.detach().clone() for k, v in policy.state_dict().items()}
        best = _BestSeen(policy)
        run_values, evaluations = [], 0
        for run in range(self.restarts):
            policy.load_state_dict(start)
            if run > 0:
                _perturb(policy, self.perturbation, generator)
            seen = _BestSeen(policy)

            def tracked(seen: _BestSeen = seen) -> Tensor:
                seen.calls += 1
                value = _checked(objective())
                seen.offer(float(value.detach()))
                return value

            params = [p for p in policy.parameters() if p.requires_grad]
            try:
                self._run(params, tracked, tick)
            except INVALID_PSI_ERRORS as err:
                log.warning("policy search run %d stopped at a numerically invalid ψ (%s); "
                            "it keeps the best ψ it evaluated", run, err)
            run_values.append(seen.value)
            evaluations += seen.calls
            if seen.state is not None and seen.value > best.value:
                best.value, best.state = seen.value, seen.state
        if best.state is None:
            raise NonFiniteObjective("no policy search run evaluated a finite predicted return")
        policy.load_state_dict(best.state)
        return SearchResult(value=best.value, evaluations=evaluations, run_values=run_values, rollouts=evaluations)

    def _search_batched(
        self,
        policy: nn.Module,
        objective: Callable[[], Tensor],
        generator: torch.Generator | None,
        tick: Callable[[], None],
    ) -> SearchResult:
        """All restarts in one joint optimisation of Σ_r V_r; the best restart's best ψ left in ``policy``."""
        if not isinstance(policy, Policy) or policy.batch_shape:
            raise TypeError(f"a batched policy search needs an unbatched qtl Policy, got {type(policy).__name__}")
        states = self.starting_states(policy, generator)
        batch = _RestartBatch(policy, states)
        try:
            self._run_batched(batch, objective, tick)
        finally:
            batch.close()
        best = max(range(self.restarts), key=lambda r: batch.best_value[r])
        if batch.best_psi[best] is None:
            raise NonFiniteObjective("no policy search run evaluated a finite predicted return")
        policy.load_state_dict({**states[0], **batch.best_psi[best]})
        return SearchResult(value=batch.best_value[best], evaluations=sum(batch.calls), run_values=batch.best_value,
                            rollouts=batch.rollouts)


class _DropRestarts(Exception):
    """Restarts (positions in the batch) whose evaluation was not finite or failed: they leave the batch."""

    def __init__(self, positions: list[int]) -> None:
        super().__init__(f"restarts at batch positions {positions} are dropped")
        self.positions = positions


class _RestartBatch:
    """The restarts still running, their ψ stacked `R' x ...` in the policy, and each restart's best ψ seen.

    While it is open, ``policy``'s parameters are the stacked ψ of the active restarts (so that
    ``objective()`` evaluates all of them in one rollout); :meth:`close` puts the plain ones back.
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
        self.params: dict[str, nn.Parameter] = {}
        self.plain = set_psi(policy, self._stacked(stack_psi(states, self.names)), (restarts,))

    def _stacked(self, psi: dict[str, Tensor]) -> dict[str, nn.Parameter]:
        """ψ `R' x ...` as the leaf parameters the optimiser moves; installed in the policy."""
        self.params = {name: nn.Parameter(value.clone(), requires_grad=self.requires_grad[name])
                       for name, value in psi.items()}
        return self.params

    def trainable(self) -> list[nn.Parameter]:
        """The stacked parameters an optimiser moves (those of ψ that require gradients)."""
        return [p for p in self.params.values() if p.requires_grad]

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

    def evaluate(self, objective: Callable[[], Tensor]) -> Tensor:
        """V `R'` of the active restarts in one rollout, each finite value offered as its restart's best.

        Raises :class:`_DropRestarts` for restarts whose value is not finite, or, when the batched
        rollout fails numerically, for those that fail alone when re-evaluated one by one.
        """
        self.rollouts += 1
        for restart in self.active:
            self.calls[restart] += 1
        try:
            values = objective()
        except INVALID_PSI_ERRORS as err:
            log.warning("batched policy search: the rollout failed (%s); re-evaluating each restart", err)
            raise _DropRestarts(self._failing_alone(objective)) from err
        if values.shape != (len(self.active),):
            raise ValueError(f"a batched policy search needs one predicted return per restart "
                             f"`{len(self.active)}`, the objective gave shape {tuple(values.shape)}")
        finite = torch.isfinite(values.detach())
        for position in range(len(self.active)):
            if finite[position]:
                self._offer(position, float(values[position].detach()))
        if not finite.all():
            raise _DropRestarts((~finite).nonzero().flatten().tolist())
        return values

    def _failing_alone(self, objective: Callable[[], Tensor]) -> list[int]:
        """Positions of the restarts whose own evaluation (value or gradient) fails; the others' values offered."""
        failing = []
        try:
            for position, restart in enumerate(self.active):
                self.rollouts += 1
                self.calls[restart] += 1
                single = {name: nn.Parameter(p[position : position + 1].detach().clone(),
                                             requires_grad=p.requires_grad) for name, p in self.params.items()}
                set_psi(self.policy, single, (1,))
                try:
                    value = objective()
                    value.sum().backward()
                except INVALID_PSI_ERRORS:
                    failing.append(position)
                    continue
                grads_finite = all(p.grad is None or bool(torch.isfinite(p.grad).all()) for p in single.values())
                if bool(torch.isfinite(value.detach()).all()) and grads_finite:
                    self._offer(position, float(value.detach().sum()))
                else:
                    failing.append(position)
        finally:
            set_psi(self.policy, self.params, (len(self.active),))
        if not failing:
            log.warning("batched policy search: no restart fails alone; every restart stops at its best ψ")
            return list(range(len(self.active)))
        return failing

    def check_gradients(self) -> None:
        """Raise :class:`_DropRestarts` for the restarts whose gradient is not finite."""
        bad = torch.zeros(len(self.active), dtype=torch.bool)
        for p in self.trainable():
            if p.grad is not None:
                bad |= ~torch.isfinite(p.grad).reshape(len(self.active), -1).all(-1).cpu()
        if bad.any():
            raise _DropRestarts(bad.nonzero().flatten().tolist())

    def drop(self, positions: list[int], *, from_best: bool) -> list[int]:
        """Remove the restarts at ``positions``; the others go on from their best (or current) ψ; the kept positions."""
        for position in positions:
            log.warning("policy search restart %d stopped at a numerically invalid ψ; it keeps the best ψ it "
                        "evaluated", self.active[position])
        kept = [position for position in range(len(self.active)) if position not in set(positions)]
        states = []
        for position in kept:
            best = self.best_psi[self.active[position]]  # set: its value at the failed evaluation was finite
            states.append(best if from_best and best is not None else self._psi_at(position))
        self.active = [self.active[position] for position in kept]
        if self.active:
            set_psi(self.policy, self._stacked(stack_psi(states, self.names)), (len(self.active),))
        return kept


class LBFGSSearch(_RestartingSearch):
    """L-BFGS with a strong-Wolfe line search, ``max_iter`` evaluations per run.

    Batched: one L-BFGS over the concatenated ψ of all restarts maximises Σ_r V_r with at most
    ``max_iter`` batched evaluations (its stopping tests apply to the joint problem). A restart
    whose value or gradient turns non-finite, or whose rollout fails alone, is dropped at its best
    ψ; the others go on from their best ψ with a fresh L-BFGS memory and the remaining budget.
    """

    def __init__(
        self, max_iter: int = 100, restarts: int = 2, perturbation: float = 0.1, batched: bool = False
    ) -> None:
        super().__init__(restarts, perturbation, batched)
        if max_iter < 1:
            raise ValueError(f"max_iter must be >= 1, got {max_iter}")
        self.max_iter = max_iter

    def _run(self, params: list[nn.Parameter], objective: Callable[[], Tensor], tick: Callable[[], None]) -> None:
        optimiser = torch.optim.LBFGS(
            params, lr=1.0, max_iter=self.max_iter, max_eval=self.max_iter, line_search_fn="strong_wolfe"
        )

        def closure() -> Tensor:
            optimiser.zero_grad()
            loss = -_checked(objective())
            loss.backward()
            for p in params:
                if p.grad is not None and not torch.isfinite(p.grad).all():
                    raise NonFiniteObjective("gradient of the predicted return is not finite")
            tick()
            return loss

        optimiser.step(closure)

    def _run_batched(self, batch: _RestartBatch, objective: Callable[[], Tensor], tick: Callable[[], None]) -> None:
        budget = self.max_iter
        while batch.active and budget > 0:
            optimiser = torch.optim.LBFGS(
                batch.trainable(), lr=1.0, max_iter=budget, max_eval=budget, line_search_fn="strong_wolfe"
            )
            used = 0

            def closure(optimiser: torch.optim.LBFGS = optimiser) -> Tensor:
                nonlocal used
                used += 1
                optimiser.zero_grad()
                loss = -batch.evaluate(objective).sum()
                loss.backward()
                batch.check_gradients()
                tick()
                return loss

            try:
                optimiser.step(closure)
                return
            except _DropRestarts as drop:
                budget -= used
                batch.drop(drop.positions, from_best=True)


class AdamSearch(_RestartingSearch):
    """Adam for ``steps`` steps per run (suits stochastic objectives).

    Batched: one Adam over the stacked ψ maximises Σ_r V_r for ``steps`` steps. Adam acts per
    element, so each restart follows the path it follows alone (up to round-off); a restart whose
    value or gradient turns non-finite, or whose rollout fails alone, is dropped at its best ψ and
    the others go on from where they are, their Adam moments kept.
    """

    def __init__(
        self, steps: int = 300, lr: float = 0.01, restarts: int = 1, perturbation: float = 0.1, batched: bool = False
    ) -> None:
        super().__init__(restarts, perturbation, batched)
        if steps < 1 or lr <= 0:
            raise ValueError(f"steps must be >= 1 and lr > 0, got {steps} and {lr}")
        self.steps, self.lr = steps, lr

    def _run(self, params: list[nn.Parameter], objective: Callable[[], Tensor], tick: Callable[[], None]) -> None:
        optimiser = torch.optim.Adam(params, lr=self.lr)
        for _ in range(self.steps):
            optimiser.zero_grad()
            loss = -_checked(objective())
            loss.backward()
            optimiser.step()
            tick()

    def _run_batched(self, batch: _RestartBatch, objective: Callable[[], Tensor], tick: Callable[[], None]) -> None:
        optimiser = torch.optim.Adam(batch.trainable(), lr=self.lr)
        step = 0
        while batch.active and step < self.steps:
            optimiser.zero_grad()
            try:
                loss = -batch.evaluate(objective).sum()
                loss.backward()
                batch.check_gradients()
            except _DropRestarts as drop:
                moved = dict(zip(batch.trainable(), [optimiser.state[p] for p in batch.trainable()], strict=True))
                kept = batch.drop(drop.positions, from_best=False)
                optimiser = torch.optim.Adam(batch.trainable(), lr=self.lr)
                for old, new in zip(moved, batch.trainable(), strict=True):
                    optimiser.state[new] = {
                        key: value[kept] if key != "step" and value.dim() > 0 else value
                        for key, value in moved[old].items()
                    }
                continue  # the same step again, for the restarts left
            optimiser.step()
            tick()
            step += 1
