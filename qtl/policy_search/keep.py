"""Which ψ a run leaves: the best it evaluated, its last, or the best of its snapshots valued afresh (``keep``)."""

from __future__ import annotations

import logging
from collections.abc import Callable

import torch
from torch import Tensor, nn

from qtl import health
from qtl.policy_search.evaluation import INVALID_PSI_ERRORS, checked, count_failure, state

log = logging.getLogger(__name__)

# Which ψ a run leaves: the best it evaluated, its last (for a noisy objective), or the best of its start, snapshots
# along the run and its last, valued afresh at the end (for a noisy objective whose run may leave a good ψ behind).
KEEP = ("best", "last", "validated")
# keep="validated": ψ is snapshotted this many times along a run (every steps // SNAPSHOTS steps), besides the last.
SNAPSHOTS = 20


def first_snapshots(keep: str, policy: nn.Module) -> list[dict[str, Tensor]]:
    """A run's snapshots before its first step: its start for ``keep="validated"``, none otherwise."""
    return [state(policy)] if keep == "validated" else []


def snapshot_due(keep: str, step: int, steps: int) -> bool:
    """Whether ``keep="validated"`` snapshots ψ after step ``step`` (0-based) of ``steps`` (the last ψ comes apart)."""
    every = max(1, steps // SNAPSHOTS)
    return keep == "validated" and (step + 1) % every == 0 and step + 1 < steps


def valued_afresh(
    policy: nn.Module, objective: Callable[[], Tensor], states: list[dict[str, Tensor]],
) -> tuple[float, dict[str, Tensor], int]:
    """The best of ``states`` by one fresh value each (no gradient), left in ``policy``; its value and the calls made.

    A state whose value fails is passed over; if every one fails, the last failure is raised.
    """
    best: tuple[float, dict[str, Tensor]] | None = None
    failures: list[Exception] = []
    for candidate in states:
        policy.load_state_dict(candidate)
        try:
            with torch.no_grad():
                value = float(checked(objective()))
        except INVALID_PSI_ERRORS as err:
            failures.append(err)
            continue
        if best is None or value > best[0]:
            best = (value, candidate)
    if best is None:
        raise failures[-1]  # the caller counts it
    for err in failures:
        count_failure(err)
    policy.load_state_dict(best[1])
    return best[0], best[1], len(states)


def kept_afresh(
    keep: str, policy: nn.Module, objective: Callable[[], Tensor], candidates: list[dict[str, Tensor]], run: int,
) -> tuple[float, dict[str, Tensor], int] | None:
    """``keep="last"``/``"validated"``: the best of run ``run``'s ``candidates`` valued afresh (:func:`valued_afresh`).

    None for ``keep="best"``, for a run without candidates, and where every candidate fails (counted, and
    its calls not counted): the run then keeps the best ψ it evaluated.
    """
    if keep == "best" or not candidates:
        return None
    try:
        return valued_afresh(policy, objective, candidates)
    except INVALID_PSI_ERRORS as err:
        count_failure(err)
        health.count(health.SEARCH_STOPPED)
        log.info("policy search run %d: its final ψ failed to evaluate (%s); it keeps the best ψ it evaluated",
                    run, err)
        return None
