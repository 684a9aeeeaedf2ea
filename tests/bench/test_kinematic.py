"""The integration comparison's config: the step set, the task's declared kinematics kept."""

from __future__ import annotations

from qtl.bench.kinematic import markdown, ratio, with_integration
from qtl.build import build
from qtl.task import Kinematics
from tests.helpers import tiny_config


def test_the_mountain_cars_declared_kinematics_are_its_five_map_steps_per_decision():
    cfg = tiny_config("task=mountaincar")
    speed = with_integration(cfg, "speed")
    assert cfg.propagation.integration == "delta" and speed.propagation.integration == "speed"  # a copy
    assert build(speed).task.kinematics == Kinematics((0,), (1,), 5.0, 0.6)


def test_kinematics_can_be_declared_from_the_command_line():
    # The schema's default is an empty node (none declared), so its keys take overrides as any other node's.
    cfg = tiny_config("task=mountaincar_continuous", "task.kinematics.positions=[0]", "task.kinematics.velocities=[1]",
                      "task.kinematics.period=5.0", "task.kinematics.weight=1.0")
    assert build(with_integration(cfg, "speed")).task.kinematics == Kinematics((0,), (1,), 5.0, 1.0)
    assert build(tiny_config("task=mountaincar_continuous")).task.kinematics is None


def test_a_declared_kinematics_is_kept():
    speed = with_integration(tiny_config(), "speed")
    assert build(speed).task.kinematics == Kinematics((0, 2), (1, 3), 0.1)


def test_ratios_are_delta_over_speed_and_the_table_shows_them():
    rows = [{"n": 250, "integration": "delta", "search_s": 9.0, "rollout_grad_s_median": 0.3},
            {"n": 250, "integration": "speed", "search_s": 3.0, "rollout_grad_s_median": 0.1}]
    assert ratio(rows, 250, "search_s") == 3.0 and ratio(rows, 500, "search_s") is None
    table = "\n".join(markdown(rows, None))
    assert "|           3.00 |" in table or "3.00" in table.splitlines()[-1]
