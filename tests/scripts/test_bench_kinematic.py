"""``scripts/bench_kinematic.py``: the verdict on kinematic against full-state learning, and its section."""

from __future__ import annotations

import math

from tests.scripts.load import script

bench_kinematic = script("bench_kinematic")


def arm(*firsts: int | None) -> list[dict]:
    """One arm's per-seed results with these first successes (None: never)."""
    return [{"seed": s, "first_success": f, "returns": [0.0, 1.0], "successes": [0, int(f is not None)],
             "model_fit_s_per_episode": 1.0, "policy_search_s_per_episode": 2.0} for s, f in enumerate(firsts)]


def test_a_seed_that_never_succeeds_counts_as_later_than_any_that_does():
    assert bench_kinematic.median_first_success(arm(3, None, None)) == math.inf
    assert bench_kinematic.median_first_success(arm(3, 5, None)) == 5


def test_speed_must_solve_four_of_five_and_be_no_later_in_median_than_delta():
    verdict = bench_kinematic.judge({"delta": arm(3, 2, None, 3, 5), "speed": arm(3, 3, None, 2, 5)}, within=8)
    assert verdict["passed"] and verdict["solved"] == 4 and verdict["median_first_success"]["speed"] == 3
    later = bench_kinematic.judge({"delta": arm(2, 2, 2, 2, 2), "speed": arm(3, 3, 3, 3, 3)}, within=8)
    assert later["passed"] is False  # all solved, but later than delta
    too_few = bench_kinematic.judge({"delta": arm(3, 3, 3, 3, 3), "speed": arm(3, 3, 3, None, 9)}, within=8)
    assert too_few["passed"] is False and too_few["solved"] == 3  # episode 9 is past --within
    partial = bench_kinematic.judge({"delta": arm(3, 3), "speed": arm(3, 3)}, within=8)
    assert partial["passed"] is None


def test_the_section_shows_both_arms_and_the_verdict():
    arms = {"delta": arm(3, 2, None, 3, 5), "speed": arm(3, 3, None, 2, 5)}
    info = {"machine": {"cpu": "cpu", "cores": 2, "torch": "2"}, "command": "cmd", "commit": "abc", "date": "d",
            "jobs": 2, "threads": 1, "episodes_per_run": 8, "within": 8, "kinematics": "dims 0 ← 1",
            "output": "docs/bench/kinematic-x.json", "verdict": bench_kinematic.judge(arms, 8), "arms": arms}
    text = "\n".join(bench_kinematic.section("x", info))
    assert "— met (4 of 5 seeds succeeded; median first success 3 (speed) vs 3 (delta))" in text
    assert text.count("| delta ") == 5 and text.count("| speed ") == 5 and "1 of 1 |" in text and "0 of 1 |" in text
