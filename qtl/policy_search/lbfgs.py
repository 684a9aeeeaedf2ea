"""Policy search by L-BFGS: torch's algorithm per run, restarts one after the other or in lockstep (batched)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import ClassVar

import torch
from torch import Tensor, nn
from torch.nn.utils import parameters_to_vector

from qtl import health
from qtl.lbfgs import INVALID, Evaluation, invalid, lbfgs
from qtl.policy_search.batch import RestartBatch
from qtl.policy_search.evaluation import INVALID_PSI_ERRORS, checked, count_failure
from qtl.policy_search.restarts import RestartingSearch
from qtl.policy_search.settings import LBFGSSettings

log = logging.getLogger(__name__)


class LBFGSSearch(RestartingSearch):
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

    settings_type: ClassVar[type[LBFGSSettings]] = LBFGSSettings
    settings: LBFGSSettings

    def __init__(self, settings: LBFGSSettings | None = None) -> None:
        super().__init__(LBFGSSettings() if settings is None else settings)

    def _run(self, policy: nn.Module, params: list[nn.Parameter], objective: Callable[[], Tensor],
             tick: Callable[[], None], generator: torch.Generator | None, snapshots: list[dict[str, Tensor]]) -> None:
        run = lbfgs(parameters_to_vector(params).detach(), self.settings.options)  # torch.optim.LBFGS's
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
            log.info("policy search run stopped: no valid ψ along its last search direction; it keeps the best "
                        "ψ it evaluated")

    def _run_batched(self, batch: RestartBatch, objective: Callable[[], Tensor], tick: Callable[[], None]) -> None:
        options = self.settings.options  # as _run's torch.optim.LBFGS
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
                        log.info("policy search restart %d stopped: no valid ψ along its last search "
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
        loss = -checked(objective())
        loss.backward()
    except INVALID_PSI_ERRORS as err:
        count_failure(err)
        return INVALID
    grad = torch.cat([p.grad.reshape(-1) if p.grad is not None else torch.zeros_like(p).reshape(-1) for p in params])
    if not bool(torch.isfinite(grad).all()):
        health.count(health.NONFINITE)
        return INVALID
    return float(loss.detach()), grad
