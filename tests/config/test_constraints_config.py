"""task.constraints: set from the CLI's override syntax, bad bounds refused in one line before any work."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from omegaconf import OmegaConf

from qtl.build import build
from qtl.config.validate import checked_task
from qtl.constraints import Constraint
from qtl.errors import TaskError
from tests.helpers import CLI_TINY, tiny_config

CART = "task.constraints=[{dim:0,low:-2.4,high:2.4,kind:terminate}]"


def cartpole_task(*constraints: dict) -> dict:
    """The default (cart-pole, 4-D state) task config as a plain dict, with ``constraints``."""
    task = OmegaConf.to_container(tiny_config().task, resolve=True)
    return {**task, "constraints": list(constraints)}


def test_constraints_default_to_an_empty_list_and_bind_nothing():
    cfg = tiny_config()
    assert OmegaConf.is_list(cfg.task.constraints) and len(cfg.task.constraints) == 0
    parts = build(cfg)
    assert parts.task.constraints == ()
    assert "constraints" not in getattr(parts.make_propagator, "keywords", {})


def test_the_override_of_the_issue_composes():
    cfg = tiny_config(CART)
    assert OmegaConf.to_container(cfg.task.constraints) == [
        {"dim": 0, "low": -2.4, "high": 2.4, "kind": "terminate", "weight": 0.0}]


def test_constraints_are_set_from_the_cli_override_syntax_and_reach_the_propagator():
    cfg = tiny_config("task.constraints=[{dim:0,low:-2.4,high:2.4,kind:terminate},"
                      "{dim:2,high:0.5,kind:penalty,weight:2}]")
    parts = build(cfg)
    expected = (Constraint(0, -2.4, 2.4, "terminate", 0.0), Constraint(2, None, 0.5, "penalty", 2.0))
    assert parts.task.constraints == expected
    assert parts.make_propagator.keywords["constraints"] == expected


@pytest.mark.parametrize(("entry", "message"), [
    ({"dim": 0, "low": 1.0, "high": 1.0}, r"task.constraints\[0\].low=1.0 must be below task.constraints\[0\].high"),
    ({"dim": 0}, r"task.constraints\[0\] bounds nothing"),
    ({"dim": 4, "high": 1.0}, r"task.constraints\[0\].dim must be a state dimension in 0..3, got 4"),
    ({"dim": -1, "high": 1.0}, r"task.constraints\[0\].dim must be a state dimension"),
    ({"dim": 0, "high": 1.0, "kind": "stop"}, r"task.constraints\[0\].kind must be one of terminate, penalty"),
    ({"dim": 0, "high": 1.0, "kind": "penalty"}, r"task.constraints\[0\].weight must be > 0 for kind=penalty"),
    ({"dim": 0, "high": 1.0, "kind": "penalty", "weight": -1}, r"weight must be > 0 for kind=penalty"),
    ({"dim": 0, "high": 1.0, "weight": 0.5}, r"task.constraints\[0\].weight must be 0 for kind=terminate"),
    ({"dim": 0, "high": "x"}, r"task.constraints\[0\].high must be a number or null"),
    ({"dim": 0, "hi": 1.0}, r"task.constraints\[0\].hi is no key of a constraint"),
])
def test_bad_constraints_are_one_line_task_errors(entry, message):
    with pytest.raises(TaskError, match=message) as raised:
        checked_task(cartpole_task(entry))
    assert "\n" not in str(raised.value)


def test_a_dimension_bounded_twice_by_one_kind_is_refused():
    with pytest.raises(TaskError, match=r"task.constraints\[1\] bounds dimension 0 \(terminate\) a second time"):
        checked_task(cartpole_task({"dim": 0, "low": -1.0}, {"dim": 0, "high": 1.0}))
    task = checked_task(cartpole_task({"dim": 0, "low": -1.0}, {"dim": 0, "high": 1.0, "kind": "penalty",
                                                               "weight": 1.0}))
    assert [c.kind for c in task.constraints] == ["terminate", "penalty"]


@pytest.mark.e2e
def test_bad_bounds_on_the_cli_are_one_line_before_any_work(tmp_path):
    environ = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    done = subprocess.run([sys.executable, "-m", "qtl", *CLI_TINY, "task.constraints=[{dim:0,low:2.4,high:-2.4}]",
                           f"hydra.run.dir={tmp_path / 'run'}"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300, env=environ)
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 1 and len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    assert "task.constraints[0].low=2.4 must be below task.constraints[0].high=-2.4" in lines[0]
    assert not (tmp_path / "run" / "metrics.csv").exists() and not (tmp_path / "run" / "checkpoints").exists()
