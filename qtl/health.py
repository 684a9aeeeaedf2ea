"""Counts of a run's numerical trouble, per episode: what the reliability table of the experiments adds up.

The parts that meet the trouble count it here (:func:`count`); the loop takes the counts after each
episode (:func:`take`) and records them in ``health.csv``. Cholesky factorisations that linear_operator
recovers by adding jitter announce it only as a ``NumericalWarning``: :func:`jitter_watch` counts those.
The counts are per process, as the runs of a sweep are (one process per job).
"""

from __future__ import annotations

import logging
import warnings
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TextIO

# The events, in the order of health.csv's columns.
NONFINITE = "nonfinite_objectives"  # policy-search evaluations whose predicted return or gradient was not finite
LINALG = "linalg_failures"  # evaluations whose rollout failed in a factorisation (LinAlgError; batched: per restart)
SEARCH_STOPPED = "search_runs_stopped"  # policy-search runs (restarts) ended early at a numerically invalid ψ
JITTER = "cholesky_jitter"  # Cholesky factorisations retried with jitter on the diagonal (recovered, or not)
GP_FIT_FAILED = "gp_fit_failures"  # GP-fit runs discarded, or resumed after a failed line-search step
CONSTANT_OUTPUTS = "constant_outputs"  # outputs a model fit found with a constant Δ and modelled as deterministic
EVENTS = (NONFINITE, LINALG, SEARCH_STOPPED, JITTER, GP_FIT_FAILED, CONSTANT_OUTPUTS)
JITTER_MESSAGE = "added jitter"  # in linear_operator's warning "A not p.d., added jitter of ... to the diagonal"

log = logging.getLogger(__name__)
_counts: Counter[str] = Counter()


def count(event: str, times: int = 1) -> None:
    """Record ``times`` occurrences of ``event`` (one of :data:`EVENTS`)."""
    if event not in EVENTS:
        raise ValueError(f"unknown health event {event!r}: one of {', '.join(EVENTS)}")
    _counts[event] += times


def take() -> dict[str, int]:
    """The counts since the last call, every event listed (0 where none), and start counting afresh."""
    taken = {event: _counts[event] for event in EVENTS}
    _counts.clear()
    return taken


@contextmanager
def jitter_watch() -> Iterator[None]:
    """Inside, count every jitter warning of linear_operator (not once per place); other warnings show as before.

    The jitter warnings themselves are logged at debug level: their counts go to ``health.csv``.
    """
    with warnings.catch_warnings():  # filters and showwarning restored on exit
        shown = warnings.showwarning
        warnings.filterwarnings("always", message=f".*{JITTER_MESSAGE}")

        def counting(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                     file: TextIO | None = None, line: str | None = None) -> None:
            if JITTER_MESSAGE in str(message):
                count(JITTER)
                log.debug("%s (%s:%d)", message, filename, lineno)
            else:
                shown(message, category, filename, lineno, file, line)

        warnings.showwarning = counting
        yield
