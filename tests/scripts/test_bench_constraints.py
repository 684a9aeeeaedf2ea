"""``scripts/bench_constraints.py``: its summaries, verdict and table, on hand-made results (no learning)."""

from __future__ import annotations

from pathlib import Path

from qtl.bench.constraints import declared_bounds
from tests.scripts.load import script

bench_constraints = script("bench_constraints")

ROOT = Path(__file__).resolve().parents[2]
WITHIN = 10


def result(arm: str, seed: int, first: int | None, crossed: list[int], cost: float | None = 0.02) -> dict:
    return {"arm": arm, "seed": seed, "first_success": first, "crossed": crossed, "crossings": sum(crossed),
            "search_s_per_evaluation": cost, "policy_search_s_per_episode": 10.0 + seed}


def arms(on_firsts: list[int | None], on_crossings: int, off_crossings: int) -> list[dict]:
    """Five seeds of 10 episodes per arm; seed 0 of each arm carries all of the arm's crossings."""
    def crossed(count: int, seed: int) -> list[int]:
        return [1] * count + [0] * (WITHIN - count) if seed == 0 else [0] * WITHIN

    off = [result("without", s, 4, crossed(off_crossings, s), 0.02) for s in range(5)]
    on = [result("with", s, first, crossed(on_crossings, s), 0.03) for s, first in enumerate(on_firsts)]
    return off + on


def summaries(results: list[dict]) -> dict[str, dict]:
    return {arm: bench_constraints.arm_summary([r for r in results if r["arm"] == arm], WITHIN)
            for arm in bench_constraints.ARMS}


def test_the_task_file_exists_and_declares_what_the_arms_switch() -> None:
    text = (ROOT / "configs" / "task" / f"{bench_constraints.TASK}.yaml").read_text()
    assert "constraints:" in text and "kind: terminate" in text and "track_limit: 0.7" in text
    assert bench_constraints.ARMS == {"without": ["task.constraints=[]"], "with": []}


def test_arm_summary_counts_seeds_in_time_crossings_and_the_mean_cost() -> None:
    results = arms([3, 9, 10, None, 2], on_crossings=2, off_crossings=7)
    got = summaries(results)
    assert got["with"] == {"seeds": 5, "solved": 3, "crossings": 2, "episodes": 50,
                           "search_s_per_evaluation": 0.03}  # episode 10 is not within 10 (0..9)
    assert got["without"]["solved"] == 5 and got["without"]["crossings"] == 7
    no_cost = [result("with", 0, 1, [0], None)]
    assert bench_constraints.arm_summary(no_cost, WITHIN)["search_s_per_evaluation"] is None


def test_verdict_needs_four_seeds_in_time_and_fewer_crossings_than_without() -> None:
    assert bench_constraints.verdict(summaries(arms([3, 4, 5, 6, None], 2, 7))) is True
    assert bench_constraints.verdict(summaries(arms([3, 4, 5, None, None], 2, 7))) is False  # 3 of 5 in time
    assert bench_constraints.verdict(summaries(arms([3, 4, 5, 6, 7], 7, 7))) is False  # as many crossings
    partial = [r for r in arms([3, 4, 5, 6, 7], 0, 7) if r["seed"] < 2]
    assert bench_constraints.verdict(summaries(partial)) is None  # not judged on 2 seeds


def test_table_has_one_row_per_arm_with_crossings_and_costs() -> None:
    results = arms([3, 4, 5, 6, None], on_crossings=2, off_crossings=7)
    table = bench_constraints.results_table(results, summaries(results), WITHIN)
    lines = table.splitlines()
    assert len(lines) == 4  # header, alignment, two arms
    assert "episodes that crossed the bound" in lines[0] and "search ms per evaluation" in lines[0]
    without, with_ = lines[2], lines[3]
    assert "task.constraints=[]" in without and "5 of 5" in without and "7 of 50 (7 0 0 0 0)" in without
    assert "`terminate` on x" in with_ and "4 of 5" in with_ and "3 4 5 6 —" in with_ and "2 of 50 (2 0 0 0 0)" in with_
    assert "30.0 ± 0.0" in with_ and "20.0 ± 0.0" in without  # ms per evaluation


def test_section_states_command_verdict_bounds_and_results_file() -> None:
    results = arms([3, 4, 5, 6, None], on_crossings=2, off_crossings=7)
    got = summaries(results)
    info = {"date": "2026-12-06", "commit": "abc1234", "command": "python scripts/bench_constraints.py",
            "machine": {"cpu": "test CPU", "cores": 2, "torch": "2.13.0"}, "jobs": 2, "threads": 1, "tag": "",
            "within": WITHIN, "episodes_per_run": WITHIN, "bounds": [{"dim": 0, "low": -0.5, "high": 0.5}],
            "results_file": "docs/bench/constraints.json", "summaries": got,
            "passed": bench_constraints.verdict(got)}
    text = bench_constraints.section(info, results)
    assert text.startswith("## State constraints: the cart-pole on a ±0.5 m track\n")
    assert "`python scripts/bench_constraints.py` at commit abc1234 — 2026-12-06, test CPU (2 cores)" in text
    assert "x[0] in [-0.5, 0.5]" in text and "`docs/bench/constraints.json`" in text
    assert "— met (4 of 5 seeds; 2 crossings with, 7 without)" in text
    assert f"{WITHIN} episodes per seed (1 random + {WITHIN - 1} learned)" in text
    three = bench_constraints.section({**info, "random_episodes": 3}, results)
    assert f"{WITHIN} episodes per seed (3 random + {WITHIN - 3} learned)" in three


def test_the_cost_line_reads_the_same_model_measurement() -> None:
    line = bench_constraints.cost_line({"seed": 0, "episode": 9, "n": 320, "repeats": 7, "with_s": 0.030,
                                        "without_s": 0.025})
    assert "n = 320" in line and "30.0 ms with the constraint and 25.0 ms without" in line and "ratio 1.20" in line


def test_a_track_limit_moves_the_env_limit_and_the_declared_bound_together() -> None:
    assert bench_constraints.track_arms(None) is bench_constraints.ARMS
    arms = bench_constraints.track_arms(0.6)
    assert arms["without"] == ["task.env.track_limit=0.6", "task.constraints=[]"]
    assert arms["with"] == ["task.env.track_limit=0.6",
                            "task.constraints=[{dim:0,low:-0.6,high:0.6,kind:terminate}]"]
    (bound,) = declared_bounds([f"task={bench_constraints.TASK}", *arms["with"]])
    assert (bound.dim, bound.low, bound.high) == (0, -0.6, 0.6)
