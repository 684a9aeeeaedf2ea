"""Policy improvement: maximise the predicted return V^π(ψ) by gradients (Algorithm 1, lines 6-9).

Restarts run one after the other, or (``batched=True``) all at once: their ψ stacked as a leading
restart dimension `R` of the policy (:mod:`qtl.policies.batching`), so that one batched rollout
evaluates all R predicted returns, and the gradient of their sum Σ_r V_r, which is block-separable,
gives each restart its own gradient. The batched search starts from the same points as the
sequential one, and each restart runs its own optimiser:

- L-BFGS: R independent runs of :func:`qtl.lbfgs.lbfgs` (torch's L-BFGS, each with its own curvature
  memory, line search and stopping tests) in lockstep: every round, each running restart asks for V
  and ∇V at one point and one batched rollout answers all of them; a restart that stops leaves the
  batch. Each restart evaluates the points the sequential search (``torch.optim.LBFGS``) evaluates;
- Adam: one Adam over the stacked ψ, which acts per element, so each restart follows its own path.

So a batched search is the sequential one up to round-off (a batched value equals the plain
policy's to ~1e-15 relative, which could in principle tip a line-search test), except that a
stochastic objective (particles with ``resample_every > 0``) advances its draws once per batched
evaluation, shared by the restarts.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import torch
from torch import Tensor, nn
from torch.nn.utils import parameters_to_vector

from qtl import health
from qtl.errors import NonFiniteObjective
from qtl.lbfgs import INVALID, Evaluation, LBFGSOptions, invalid, lbfgs
from qtl.plateau import PlateauMonitor, PlateauRule
from qtl.policies import Policy, psi_names, set_psi, stack_psi

log = logging.getLogger(__name__)

# Parameters with a spread below this are perturbed on this scale instead.
MIN_PERTURBATION_SCALE = 1e-3
# Which ψ a run leaves: the best it evaluated, its last (for a noisy objective), or the best of its start, snapshots
# along the run and its last, valued afresh at the end (for a noisy objective whose run may leave a good ψ behind).
KEEP = ("best", "last", "validated")
# keep="validated": ψ is snapshotted this many times along a run (every steps // SNAPSHOTS steps), besides the last.
SNAPSHOTS = 20
# Errors of an evaluation at a numerically invalid ψ: they end a run (sequential) or drop a restart (batched).
INVALID_PSI_ERRORS = (NonFiniteObjective, torch.linalg.LinAlgError)


@dataclass(frozen=True)
class SearchResult:
    """Outcome of a policy search: the best predicted return and what it cost.

    ``evaluations`` counts evaluations of one restart's predicted return, failed ones included: a
    batched rollout of R restarts counts R, so that sequential and batched searches compare;
    ``run_evaluations`` splits it by run. ``rollouts`` counts calls of the objective: equal to
    ``evaluations`` when sequential, one per batched rollout (plus the single-restart
    re-evaluations that locate a failure) when batched.
    """

    value: float
    evaluations: int
    run_values: list[float]  # best value of each run (-inf for a run that evaluated nothing finite)
    rollouts: int
    run_evaluations: list[int] = field(default_factory=list)  # evaluations of each run, failed ones included


def _perturb(policy: nn.Module, scale: float, generator: torch.Generator | None) -> None:
    """ψ ← ψ + scale · spread(ψ) · ε, ε ~ N(0, I), per parameter tensor."""
    with torch.no_grad():
        for p in policy.parameters():
            spread = p.std() if p.numel() > 1 else p.abs().squeeze()
            spread = max(float(spread), MIN_PERTURBATION_SCALE)
            noise = torch.randn(p.shape, generator=generator, dtype=p.dtype).to(p.device)
            p.add_(scale * spread * noise)


def _child_generator(generator: torch.Generator | None) -> torch.Generator:
    """A generator seeded from ``generator`` (or torch's global one): the dropout masks' stream."""
    seed = int(torch.randint(2**62, (1,), generator=generator))
    return torch.Generator().manual_seed(seed)


def _count_failure(err: BaseException) -> None:
    """Count an evaluation that failed: a non-finite value or gradient, or a failed factorisation."""
    health.count(health.NONFINITE if isinstance(err, NonFiniteObjective) else health.LINALG)


def _checked(value: Tensor) -> Tensor:
    if not torch.isfinite(value).all():
        raise NonFiniteObjective(f"predicted return is {value.item()}")
    return value


def _state(policy: nn.Module) -> dict[str, Tensor]:
    """A copy of ``policy``'s ψ."""
    return {k: v.detach().clone() for k, v in policy.state_dict().items()}


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
            self.state = _state(self.policy)


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

    keep = "best"  # which ψ a run leaves (see KEEP)

    def _run(self, policy: nn.Module, params: list[nn.Parameter], objective: Callable[[], Tensor],
             tick: Callable[[], None], generator: torch.Generator | None, snapshots: list[dict[str, Tensor]]) -> None:
        """A run from the ψ in ``policy``; with ``keep="validated"`` it appends snapshots of ψ to ``snapshots``."""
        raise NotImplementedError

    def _run_batched(self, batch: _RestartBatch, objective: Callable[[], Tensor], tick: Callable[[], None]) -> None:
        raise NotImplementedError

    def starting_states(
        self, policy: nn.Module, generator: torch.Generator | None = None
    ) -> list[dict[str, Tensor]]:
        """Every restart's starting ψ: the current one, then perturbations drawn in the sequential search's order."""
        start = _state(policy)
        states = [start]
        for _ in range(1, self.restarts):
            policy.load_state_dict(start)
            _perturb(policy, self.perturbation, generator)
            states.append(_state(policy))
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
        start = _state(policy)
        best = _BestSeen(policy)
        run_values, run_evaluations = [], []
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
            snapshots = [_state(policy)] if self.keep == "validated" else []  # the run's start is one
            candidates: list[dict[str, Tensor]] = []
            try:
                self._run(policy, params, tracked, tick, generator, snapshots)
                candidates = [*snapshots, _state(policy)]
            except INVALID_PSI_ERRORS as err:
                _count_failure(err)
                health.count(health.SEARCH_STOPPED)
                candidates = snapshots  # taken before the invalid ψ; without any, the best ψ evaluated
                log.warning("policy search run %d stopped at a numerically invalid ψ (%s); it keeps the best ψ %s",
                            run, err, "of its snapshots" if candidates else "it evaluated")
            if self.keep != "best" and candidates:  # the final ψ (and the snapshots), valued afresh (no dropout now)
                try:
                    seen.value, seen.state, calls = _valued_afresh(policy, objective, candidates)
                    seen.calls += calls
                except INVALID_PSI_ERRORS as err:
                    _count_failure(err)
                    health.count(health.SEARCH_STOPPED)
                    log.warning("policy search run %d: its final ψ failed to evaluate (%s); it keeps the best ψ it "
                                "evaluated", run, err)
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
                            rollouts=batch.rollouts, run_evaluations=batch.calls)


def _valued_afresh(
    policy: nn.Module, objective: Callable[[], Tensor], states: list[dict[str, Tensor]],
) -> tuple[float, dict[str, Tensor], int]:
    """The best of ``states`` by one fresh value each (no gradient), left in ``policy``; its value and the calls made.

    A state whose value fails is passed over; if every one fails, the last failure is raised.
    """
    best: tuple[float, dict[str, Tensor]] | None = None
    failures: list[Exception] = []
    for state in states:
        policy.load_state_dict(state)
        try:
            with torch.no_grad():
                value = float(_checked(objective()))
        except INVALID_PSI_ERRORS as err:
            failures.append(err)
            continue
        if best is None or value > best[0]:
            best = (value, state)
    if best is None:
        raise failures[-1]  # the run's own handler counts it
    for err in failures:
        _count_failure(err)
    policy.load_state_dict(best[1])
    return best[0], best[1], len(states)


class _DropRestarts(Exception):
    """Restarts (positions in the batch) whose evaluation was not finite or failed: they leave the batch."""

    def __init__(self, positions: list[int]) -> None:
        super().__init__(f"restarts at batch positions {positions} are dropped")
        self.positions = positions


class _RestartBatch:
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

    def evaluate_each(self, objective: Callable[[], Tensor]) -> list[Evaluation]:
        """(−V_r, −∂V_r/∂ψ_r flattened `n`) of each active restart from one rollout; INVALID where either is not finite.

        Each finite value is offered as its restart's best. When the batched rollout fails
        numerically, each restart is evaluated alone (as the sequential search would).
        """
        self.rollouts += 1
        for restart in self.active:
            self.calls[restart] += 1
        try:
            values = objective()
            self._check_shape(values)
            (-values.sum()).backward()
        except INVALID_PSI_ERRORS as err:
            _count_failure(err)
            log.warning("batched policy search: the rollout failed (%s); evaluating each restart alone", err)
            alone = self._alone(objective)
            return [self._answer(position, value, grad) for position, (value, grad) in enumerate(alone)]
        params = self.trainable()
        return [self._answer(position, values[position].detach(), _flat_grad(params, position))
                for position in range(len(self.active))]

    def _answer(self, position: int, value: Tensor | None, grad: Tensor | None) -> Evaluation:
        """The evaluation an optimiser receives for the restart at ``position``; a finite value is offered."""
        if value is None or grad is None:  # failed alone: counted there
            return INVALID
        if not bool(torch.isfinite(value)):
            health.count(health.NONFINITE)
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
            _count_failure(err)
            log.warning("batched policy search: the rollout failed (%s); re-evaluating each restart", err)
            raise _DropRestarts(self._failing_alone(objective)) from err
        self._check_shape(values)
        finite = torch.isfinite(values.detach())
        for position in range(len(self.active)):
            if finite[position]:
                self._offer(position, float(values[position].detach()))
        if not finite.all():
            health.count(health.NONFINITE, int((~finite).sum()))
            raise _DropRestarts((~finite).nonzero().flatten().tolist())
        return values

    def _alone(self, objective: Callable[[], Tensor]) -> list[tuple[Tensor | None, Tensor | None]]:
        """V and −∂V/∂ψ flattened `n` of each active restart evaluated alone, both None where that raises."""
        found: list[tuple[Tensor | None, Tensor | None]] = []
        try:
            for position, restart in enumerate(self.active):
                self.rollouts += 1
                self.calls[restart] += 1
                single = {name: nn.Parameter(p[position : position + 1].detach().clone(),
                                             requires_grad=p.requires_grad) for name, p in self.params.items()}
                set_psi(self.policy, single, (1,))
                try:
                    value = objective()
                    (-value.sum()).backward()
                except INVALID_PSI_ERRORS as err:
                    _count_failure(err)
                    found.append((None, None))
                    continue
                trainable = [p for p in single.values() if p.requires_grad]
                found.append((value.detach().sum(), _flat_grad(trainable, 0)))
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
            health.count(health.NONFINITE, int(bad.sum()))
            raise _DropRestarts(bad.nonzero().flatten().tolist())

    def drop(self, positions: list[int]) -> list[int]:
        """Remove the restarts at ``positions``; the others go on from their current ψ; the kept positions."""
        for position in positions:
            health.count(health.SEARCH_STOPPED)
            log.warning("policy search restart %d stopped at a numerically invalid ψ; it keeps the best ψ it "
                        "evaluated", self.active[position])
        kept = [position for position in range(len(self.active)) if position not in set(positions)]
        states = [self._psi_at(position) for position in kept]
        self.active = [self.active[position] for position in kept]
        if self.active:
            set_psi(self.policy, self._stacked(stack_psi(states, self.names)), (len(self.active),))
        return kept


def _flat_grad(params: list[nn.Parameter], position: int) -> Tensor:
    """The gradient of the restart at ``position`` of stacked ``params``, flattened `n` (zeros where there is none)."""
    return torch.cat([p.grad[position].reshape(-1) if p.grad is not None else p.new_zeros(p[position].numel())
                      for p in params])


class LBFGSSearch(_RestartingSearch):
    """L-BFGS with a strong-Wolfe line search, ``max_iter`` iterations and evaluations per run (torch's LBFGS).

    Sequential: ``torch.optim.LBFGS`` per run. Batched: each restart runs its own
    :func:`qtl.lbfgs.lbfgs` (the same algorithm, its own memory, line search, stopping tests and
    budget); they advance in lockstep, one batched rollout per round answering every running
    restart's request, and a restart leaves the batch when it stops. So each restart evaluates the
    points it evaluates in the sequential search (up to round-off between batched and plain
    rollouts). A restart whose value or gradient turns non-finite, or whose rollout fails alone,
    stops at its best ψ, as a sequential run does; when a batched rollout fails, its restarts are
    evaluated one by one for that round.
    """

    def __init__(
        self, max_iter: int = 100, restarts: int = 2, perturbation: float = 0.1, batched: bool = False
    ) -> None:
        super().__init__(restarts, perturbation, batched)
        if max_iter < 1:
            raise ValueError(f"max_iter must be >= 1, got {max_iter}")
        self.max_iter = max_iter

    def _run(self, policy: nn.Module, params: list[nn.Parameter], objective: Callable[[], Tensor],
             tick: Callable[[], None], generator: torch.Generator | None, snapshots: list[dict[str, Tensor]]) -> None:
        options = LBFGSOptions(max_iter=self.max_iter, max_eval=self.max_iter)  # torch.optim.LBFGS's settings
        run = lbfgs(parameters_to_vector(params).detach(), options)
        point, answer = next(run), None
        while True:
            _assign(params, point)
            answer = _evaluate_flat(params, objective)
            if not invalid(answer):
                tick()
            try:
                point = run.send(answer)
            except StopIteration as stop:
                _assign(params, stop.value)  # the last accepted point, where torch's LBFGS leaves ψ
                break
        if invalid(answer):  # it ended on an invalid point: no valid step was left to take
            health.count(health.SEARCH_STOPPED)
            log.warning("policy search run stopped: no valid ψ along its last search direction; it keeps the best "
                        "ψ it evaluated")

    def _run_batched(self, batch: _RestartBatch, objective: Callable[[], Tensor], tick: Callable[[], None]) -> None:
        options = LBFGSOptions(max_iter=self.max_iter, max_eval=self.max_iter)  # as _run's torch.optim.LBFGS
        runs = {restart: lbfgs(batch.point(position), options) for position, restart in enumerate(batch.active)}
        asked = {restart: next(run) for restart, run in runs.items()}  # restart → the point it wants evaluated
        while asked:
            batch.load(asked)
            answers = batch.evaluate_each(objective)
            tick()
            for restart, answer in zip(list(asked), answers, strict=True):
                try:
                    asked[restart] = runs[restart].send(answer)
                except StopIteration:  # converged, out of budget, or no valid step left: it leaves the batch
                    del asked[restart]
                    if invalid(answer):
                        health.count(health.SEARCH_STOPPED)
                        log.warning("policy search restart %d stopped: no valid ψ along its last search "
                                    "direction; it keeps the best ψ it evaluated", restart)


def _assign(params: list[nn.Parameter], point: Tensor) -> None:
    """Set ``params`` to the flat ``point`` `n` (in order, as ``torch.optim.LBFGS`` flattens them)."""
    offset = 0
    with torch.no_grad():
        for p in params:
            p.copy_(point[offset : offset + p.numel()].view_as(p))
            offset += p.numel()


def _evaluate_flat(params: list[nn.Parameter], objective: Callable[[], Tensor]) -> Evaluation:
    """(−V, −∂V/∂ψ flattened `n`) at the current ψ; (inf, None) where ψ is numerically invalid (counted)."""
    for p in params:
        p.grad = None
    try:
        loss = -_checked(objective())
        loss.backward()
    except INVALID_PSI_ERRORS as err:
        _count_failure(err)
        return INVALID
    grad = torch.cat([p.grad.reshape(-1) if p.grad is not None else torch.zeros_like(p).reshape(-1) for p in params])
    if not bool(torch.isfinite(grad).all()):
        health.count(health.NONFINITE)
        return INVALID
    return float(loss.detach()), grad


def _short(name: str) -> str:
    """A parameter's own name, without the modules that hold it (``policy.support_points`` → ``support_points``)."""
    return name.rsplit(".", 1)[-1]


def _named(policy: nn.Module, params: list[nn.Parameter]) -> dict[str, nn.Parameter]:
    """``params`` by their names in ``policy``."""
    ids = {id(p) for p in params}
    return {name: p for name, p in policy.named_parameters() if id(p) in ids}


class AdamSearch(_RestartingSearch):
    """Adam for ``steps`` steps per run (suits stochastic objectives).

    Batched: one Adam over the stacked ψ maximises Σ_r V_r for ``steps`` steps. Adam acts per
    element, so each restart follows the path it follows alone (up to round-off); a restart whose
    value or gradient turns non-finite, or whose rollout fails alone, is dropped at its best ψ and
    the others go on from where they are, their Adam moments kept.

    MC-PILCO's schedule (sequential runs): ``dropout`` p > 0 drops the policy's basis functions at
    random during the search (:meth:`~qtl.policies.Policy.set_dropout`); with ``plateau`` (a
    :class:`~qtl.plateau.PlateauRule`) a plateau of the objective multiplies the learning rate by
    ``lr_reduction`` (not below ``lr_min``), lowers p by ``dropout_reduction`` and restarts Adam's
    moments, and a plateau at ``lr_min`` ends the run early. ``keep``: ``best`` (the best ψ seen,
    for a deterministic objective), ``last`` (the final ψ, valued by one more evaluation without
    dropout: the best of many noisy values is biased) or ``validated`` (the run's start, ``SNAPSHOTS``
    snapshots along the run and the final ψ, each valued by one more evaluation without dropout, the best
    of them: a noisy search can leave a good ψ behind, and never leaves a worse one than it began with).
    """

    def __init__(
        self,
        steps: int = 300,
        lr: float = 0.01,
        restarts: int = 1,
        perturbation: float = 0.1,
        batched: bool = False,
        *,
        keep: str = "best",
        dropout: float = 0.0,
        dropout_reduction: float = 0.125,
        plateau: PlateauRule | Mapping[str, float] | None = None,
        lr_reduction: float = 0.5,
        lr_min: float = 0.0025,
        lr_scales: Mapping[str, float] | None = None,
    ) -> None:
        super().__init__(restarts, perturbation, batched)
        if steps < 1 or lr <= 0:
            raise ValueError(f"steps must be >= 1 and lr > 0, got {steps} and {lr}")
        if keep not in KEEP:
            raise ValueError(f"keep must be one of {', '.join(KEEP)}, got {keep!r}")
        if not 0.0 <= dropout < 1.0 or dropout_reduction < 0:
            raise ValueError(f"dropout must be in [0, 1) and dropout_reduction >= 0, got {dropout} and "
                             f"{dropout_reduction}")
        if not 0.0 < lr_reduction <= 1.0 or not 0.0 <= lr_min <= lr:
            raise ValueError(f"lr_reduction must be in (0, 1] and lr_min in [0, lr], got {lr_reduction} and {lr_min}")
        if plateau is not None and not isinstance(plateau, PlateauRule):
            plateau = PlateauRule(**plateau)
        scheduled = keep != "best" or dropout > 0 or plateau is not None
        if scheduled and batched and restarts > 1:
            raise ValueError("optimizer.keep=last, optimizer.dropout and optimizer.plateau run restarts one after "
                             "the other: set optimizer.batched=false or optimizer.restarts=1")
        self.steps, self.lr = steps, lr
        self.keep = keep
        self.dropout, self.dropout_reduction = float(dropout), float(dropout_reduction)
        self.plateau = plateau
        self.lr_reduction, self.lr_min = float(lr_reduction), float(lr_min)
        self.lr_scales = {str(k): float(v) for k, v in (lr_scales or {}).items()}
        if any(not v > 0 for v in self.lr_scales.values()):
            raise ValueError(f"lr_scales must be > 0, got {self.lr_scales}")
        if scheduled:
            self.batched = False  # one restart: the sequential run is the batched one

    def _run(self, policy: nn.Module, params: list[nn.Parameter], objective: Callable[[], Tensor],
             tick: Callable[[], None], generator: torch.Generator | None, snapshots: list[dict[str, Tensor]]) -> None:
        lr, dropout = self.lr, self.dropout
        if dropout > 0:
            policy.set_dropout(dropout, _child_generator(generator))
        try:
            named = _named(policy, params)
            optimiser = torch.optim.Adam(self.param_groups(named, lr), lr=lr)
            monitor = None
            every = max(1, self.steps // SNAPSHOTS)
            for step in range(self.steps):
                optimiser.zero_grad()
                value = _checked(objective())
                (-value).backward()
                optimiser.step()
                tick()
                if self.keep == "validated" and (step + 1) % every == 0 and step + 1 < self.steps:
                    snapshots.append(_state(policy))
                if self.plateau is None:
                    continue
                if monitor is None:
                    monitor = PlateauMonitor(self.plateau, float(value.detach()))
                    continue
                if not monitor.update(float(value.detach())):
                    continue
                if lr <= self.lr_min:
                    log.info("policy search: plateau at lr %.4g after %d steps: stopped", lr, monitor.step + 1)
                    break
                lr = max(lr * self.lr_reduction, self.lr_min)
                dropout = max(dropout - self.dropout_reduction, 0.0)
                log.info("policy search: plateau after %d steps: lr %.4g, dropout %.3g", monitor.step + 1, lr, dropout)
                monitor.annealed()
                policy.set_dropout(dropout, _child_generator(generator) if dropout > 0 else None)
                optimiser = torch.optim.Adam(self.param_groups(named, lr), lr=lr)
        finally:
            if self.dropout > 0:
                policy.set_dropout(0.0)

    def param_groups(self, named: Mapping[str, nn.Parameter], lr: float) -> list[dict]:
        """Adam's parameter groups: each of ψ's parameters at ``lr`` × its ``lr_scales`` factor (1 if unnamed there)."""
        unknown = set(self.lr_scales) - {_short(name) for name in named}
        if unknown:
            raise ValueError(f"optimizer.lr_scales names {sorted(unknown)}, which this policy does not have: "
                             f"choose from {sorted({_short(name) for name in named})}")
        return [{"params": [p], "lr": lr * self.lr_scales.get(_short(name), 1.0)} for name, p in named.items()]

    def _run_batched(self, batch: _RestartBatch, objective: Callable[[], Tensor], tick: Callable[[], None]) -> None:
        optimiser = torch.optim.Adam(self.param_groups(batch.trainable_named(), self.lr), lr=self.lr)
        step = 0
        while batch.active and step < self.steps:
            optimiser.zero_grad()
            try:
                loss = -batch.evaluate(objective).sum()
                loss.backward()
                batch.check_gradients()
            except _DropRestarts as drop:
                moved = dict(zip(batch.trainable(), [optimiser.state[p] for p in batch.trainable()], strict=True))
                kept = batch.drop(drop.positions)
                optimiser = torch.optim.Adam(self.param_groups(batch.trainable_named(), self.lr), lr=self.lr)
                for old, new in zip(moved, batch.trainable(), strict=True):
                    optimiser.state[new] = {
                        key: value[kept] if key != "step" and value.dim() > 0 else value
                        for key, value in moved[old].items()
                    }
                continue  # the same step again, for the restarts left
            optimiser.step()
            tick()
            step += 1
