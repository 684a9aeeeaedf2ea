"""Constraints in the loop: survival and crossings in metrics.csv and TensorBoard, the shaded figure, old runs."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import torch
from omegaconf import OmegaConf

from qtl.checkpoint import latest_checkpoint
from qtl.constraints import Constraint
from qtl.loop import run
from qtl.recorder import trajectory_figure
from qtl.train import resume_config
from tests.helpers import tiny_config
from tests.test_recorder import scalars

# A cart track of ±0.3 m (terminate) and a pole-angle cost (penalty) on the default cart-pole task.
CONSTRAINED = "task.constraints=[{dim:0,low:-0.3,high:0.3},{dim:2,high:3.5,kind:penalty,weight:0.5}]"
NEW_COLUMNS = ("predicted_survival", "survival_half_step", "crossed")


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_a_constrained_run_records_survival_and_crossings(tmp_path):
    run(tiny_config("episodes=1", CONSTRAINED), tmp_path)
    rows = read_csv(tmp_path / "metrics.csv")
    assert math.isnan(float(rows[0]["predicted_survival"]))  # the random episode predicts nothing
    survival = float(rows[1]["predicted_survival"])
    assert 0.0 < survival < 1.0
    half = rows[1]["survival_half_step"]
    assert half in ("", "nan") or 1 <= int(float(half)) <= 8
    assert all(r["crossed"] in ("0", "1") for r in rows)
    tags = scalars(tmp_path)
    assert tags["policy/predicted_survival"] == [(1, tags["policy/predicted_survival"][0][1])]
    assert abs(tags["policy/predicted_survival"][0][1] - survival) < 1e-6  # TensorBoard keeps float32
    assert [step for step, _ in tags["eval/crossed"]] == [0, 1]


def test_an_unconstrained_run_records_neutral_values(tmp_path):
    run(tiny_config("episodes=1"), tmp_path)
    rows = read_csv(tmp_path / "metrics.csv")
    assert float(rows[1]["predicted_survival"]) == 1.0 and math.isnan(float(rows[1]["survival_half_step"]))
    assert [r["crossed"] for r in rows] == ["0", "0"]


def test_a_run_recorded_before_the_columns_resumes_with_them_empty(tmp_path):
    # Rows of a checkpoint written before the constraint columns (and a config without task.constraints) resume:
    # the old rows keep their values with the new columns empty, the new rows have them.
    run(tiny_config("episodes=2"), tmp_path / "whole")
    split = tmp_path / "split"
    run(tiny_config("episodes=1"), split)
    path = latest_checkpoint(split)
    state = torch.load(path, weights_only=True)
    state["metrics"] = [{k: v for k, v in row.items() if k not in NEW_COLUMNS} for row in state["metrics"]]
    cfg = OmegaConf.create(state["config"])
    cfg.task = {k: v for k, v in cfg.task.items() if k != "constraints"}
    state["config"] = OmegaConf.to_yaml(cfg)
    torch.save(state, path)
    run(resume_config(split, ["episodes=2"]), split, resume=True)
    old, whole = read_csv(split / "metrics.csv"), read_csv(tmp_path / "whole" / "metrics.csv")
    assert [[r[c] for c in NEW_COLUMNS] for r in old[:2]] == [["", "", ""]] * 2
    assert [r[c] for c in NEW_COLUMNS for r in old[2:]] == [r[c] for c in NEW_COLUMNS for r in whole[2:]]
    assert [{k: v for k, v in r.items() if k not in NEW_COLUMNS} for r in old] == \
        [{k: v for k, v in r.items() if k not in NEW_COLUMNS} for r in whole]


def test_the_prediction_figure_shades_beyond_the_bounds():
    steps = np.arange(5)
    mean = np.stack([0.1 * steps, np.zeros(5)], axis=1)
    std = np.full((5, 2), 0.05)
    bounds = (Constraint(0, low=-0.3, high=0.3), Constraint(1, high=1.0, kind="penalty", weight=1.0))
    fig = trajectory_figure(mean, std, mean[:3], "bounds", constraints=bounds)
    try:
        top, bottom = fig.axes
        shaded = [p for p in top.patches if p.get_label().startswith("outside bounds")]
        assert len(top.patches) == 2 and len(shaded) == 1  # below low and above high; one legend entry
        assert top.get_ylim()[0] < -0.3 and top.get_ylim()[1] > 0.4  # both bounds and the data in view
        assert len(bottom.patches) == 1 and bottom.get_ylim()[1] > 1.0
    finally:
        plt.close(fig)
