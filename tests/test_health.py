"""qtl.health: the per-episode counts of numerical trouble, and the count of linear_operator's jitter warnings."""

from __future__ import annotations

import warnings

import pytest
import torch
from linear_operator.utils.cholesky import psd_safe_cholesky

from qtl import health


def test_take_returns_every_event_and_starts_afresh():
    health.take()
    health.count(health.NONFINITE)
    health.count(health.GP_FIT_FAILED, 3)
    assert health.take() == {**dict.fromkeys(health.EVENTS, 0), health.NONFINITE: 1, health.GP_FIT_FAILED: 3}
    assert health.take() == dict.fromkeys(health.EVENTS, 0)


def test_an_unknown_event_is_named():
    with pytest.raises(ValueError, match="unknown health event 'nan'"):
        health.count("nan")


def test_jitter_watch_counts_every_jitter_and_lets_other_warnings_through():
    singular = torch.ones(3, 3, dtype=torch.float64)  # rank 1: needs jitter on the diagonal
    health.take()
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        with health.jitter_watch():
            for _ in range(3):  # the same place thrice: a "default" filter would show (and count) it once
                psd_safe_cholesky(singular)
            warnings.warn("still shown", UserWarning, stacklevel=1)
    assert [str(w.message) for w in shown] == ["still shown"]  # the jitter warnings were counted instead
    jitters = health.take()[health.JITTER]
    assert jitters >= 3 and jitters % 3 == 0  # each call retries the same number of times
    with warnings.catch_warnings(record=True) as caught:  # outside the watch: plain warnings again, not counted
        warnings.simplefilter("always")
        psd_safe_cholesky(singular)
    assert caught and health.take()[health.JITTER] == 0
