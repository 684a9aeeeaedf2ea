"""What a policy search returns: the best predicted return it found and what it cost."""

from __future__ import annotations

from dataclasses import dataclass, field


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
