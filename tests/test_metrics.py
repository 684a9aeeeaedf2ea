"""Learning-curve summaries on hand-computed curves (Section 5's Tables 1-3)."""

from __future__ import annotations

import pytest

from qtl.metrics import (
    Curve,
    area_under_curve,
    final_performance,
    final_successes,
    first_success,
    relapses,
    time_to_convergence,
)

RETURNS = [0.0, 2.0, 10.0, 30.0, 36.0, 38.0, 37.0]


def test_final_performance_is_the_mean_of_the_last_three():
    assert final_performance(RETURNS) == pytest.approx((36.0 + 38.0 + 37.0) / 3)
    assert final_performance([5.0]) == 5.0
    with pytest.raises(ValueError, match="at least one episode"):
        final_performance([])


def test_area_under_curve_is_the_trapezoid_over_episodes():
    # (0+2)/2 + (2+10)/2 + (10+30)/2 + (30+36)/2 + (36+38)/2 + (38+37)/2 = 1 + 6 + 20 + 33 + 37 + 37.5
    assert area_under_curve(RETURNS) == pytest.approx(134.5)
    assert area_under_curve([4.0]) == 4.0


def test_time_to_convergence_is_the_first_episode_at_95_percent_of_final():
    # final 37, 95 % = 35.15: episode 4 (36) is the first at or above it
    assert time_to_convergence(RETURNS) == 4
    assert time_to_convergence([1.0, 1.0, 1.0]) == 0


def test_first_success():
    assert first_success([0, 0, 1, 0, 1]) == 2
    assert first_success([False, False]) is None


def test_relapses_count_the_failures_after_the_first_success():
    assert relapses([0, 0, 1, 0, 1, 1, 0]) == 2  # episodes 3 and 6
    assert relapses([0, 1, 1, 1]) == 0
    assert relapses([True]) == 0
    assert relapses([0, 0, 0]) is None  # no success: nothing to relapse from


def test_final_successes_count_the_last_three_episodes():
    assert final_successes([1, 1, 1, 0, 1, 0]) == 1
    assert final_successes([0, 1, 1, 1]) == 3
    assert final_successes([1, 0]) == 1  # a curve shorter than three: all of it
    assert final_successes([1, 1, 0, 1, 1], last=2) == 2
    with pytest.raises(ValueError, match="at least one episode"):
        final_successes([])


def test_curve_reads_a_prefix_of_metrics_csv(tmp_path):
    rows = ["episode,kind,return,success,compliance", "0,random,0.5,0,", "1,policy,20.0,0,0.61",
            "2,policy,35.0,1,0.55"]
    (tmp_path / "metrics.csv").write_text("\n".join(rows) + "\n")
    curve = Curve.read(tmp_path)
    assert curve.returns == [0.5, 20.0, 35.0] and curve.successes == [False, False, True]
    assert curve.compliance[1:] == [0.61, 0.55]
    assert Curve.read(tmp_path, 2).returns == [0.5, 20.0]
    assert curve.summary()["first_success"] == 2
    with pytest.raises(ValueError, match="3 episodes, 4 needed"):
        Curve.read(tmp_path, 4)
