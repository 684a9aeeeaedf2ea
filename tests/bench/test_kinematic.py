"""The integration comparison's config: the step set, and a task's known kinematics where its YAML has none."""

from __future__ import annotations

from qtl.bench.kinematic import markdown, ratio, with_integration
from qtl.build import build
from qtl.task import Kinematics
from tests.helpers import tiny_config


def test_speed_gets_the_known_kinematics_of_a_task_that_declares_none():
    cfg = tiny_config("task=mountaincar")
    speed = with_integration(cfg, "speed")
    assert cfg.task.kinematics is None and cfg.propagation.integration == "delta"  # the original is left alone
    assert build(speed).task.kinematics == Kinematics((0,), (1,), 1.0)
    assert with_integration(cfg, "delta").task.kinematics is None


def test_a_declared_kinematics_is_kept():
    speed = with_integration(tiny_config(), "speed")
    assert build(speed).task.kinematics == Kinematics((0, 2), (1, 3), 0.1)


def test_ratios_are_delta_over_speed_and_the_table_shows_them():
    rows = [{"n": 250, "integration": "delta", "search_s": 9.0, "rollout_grad_s_median": 0.3},
            {"n": 250, "integration": "speed", "search_s": 3.0, "rollout_grad_s_median": 0.1}]
    assert ratio(rows, 250, "search_s") == 3.0 and ratio(rows, 500, "search_s") is None
    table = "\n".join(markdown(rows, None))
    assert "|           3.00 |" in table or "3.00" in table.splitlines()[-1]
