"""The run recorder: metrics.csv and timings.csv rows, TensorBoard scalars read back, θ columns both ways."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from qtl.models import GPHyperparameters
from qtl.recorder import (
    BASE_COLUMNS,
    METRICS_FILE,
    THETA_P_PREFIX,
    TIMINGS_FILE,
    Records,
    RunRecorder,
    start_columns,
    start_row,
    theta_columns,
    theta_from_row,
    theta_row,
    trajectory_figure,
)

THETA = GPHyperparameters(
    lengthscales=torch.tensor([[1.5, 0.25, 3.0], [2.0, 0.5, 1.0 / 3.0]], dtype=torch.float64),
    signal_variance=torch.tensor([0.7, 1.1], dtype=torch.float64),
    noise_variance=torch.tensor([1e-6, 2e-4], dtype=torch.float64),
)
COLUMNS = BASE_COLUMNS + theta_columns(2, 3)


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def episode_row(episode: int, theta: GPHyperparameters | None) -> dict[str, float | int | str]:
    return {"episode": episode, "kind": "random" if episode == 0 else "policy", "return": 10.0 * episode + 0.5,
            "success": int(episode == 2), "compliance": "", **theta_row(theta)}


def scalars(run_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar tag of the run's event files: (step, value) pairs."""
    events = EventAccumulator(str(run_dir))
    events.Reload()
    return {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}


def test_theta_columns_name_every_hyperparameter_and_parse_back():
    assert theta_columns(2, 3)[:5] == ["theta/out0/lengthscale/in0", "theta/out0/lengthscale/in1",
                                       "theta/out0/lengthscale/in2", "theta/out0/signal_variance",
                                       "theta/out0/noise_variance"]
    assert theta_columns(1, 1, THETA_P_PREFIX) == ["theta_p/out0/lengthscale/in0", "theta_p/out0/signal_variance",
                                                   "theta_p/out0/noise_variance"]
    row = theta_row(THETA)
    assert list(row) == theta_columns(2, 3)  # the same names, in the same order
    assert theta_from_row(row).natural().equal(THETA.natural())
    # As read back from metrics.csv: strings in full precision, θ_p beside θ, empty where there is no model.
    text = {k: repr(v) for k, v in {**row, **theta_row(THETA, THETA_P_PREFIX)}.items()}
    assert theta_from_row(text, THETA_P_PREFIX).natural().equal(THETA.natural())
    assert theta_from_row({c: "" for c in theta_columns(2, 3)}) is None
    assert theta_row(None) == {}


def test_theta_columns_name_the_state_dimensions_the_outputs_model():
    # Speed integration on the cart-pole: the GP's two outputs are ẋ and θ̇, state dimensions 1 and 3.
    columns = theta_columns(2, 3, outputs=(1, 3))
    assert columns[0] == "theta/out1/lengthscale/in0" and columns[-1] == "theta/out3/noise_variance"
    row = theta_row(THETA, outputs=(1, 3))
    assert list(row) == columns
    assert theta_from_row(row).natural().equal(THETA.natural())


def test_recorder_writes_rows_and_scalars_and_a_resume_keeps_exactly_the_earlier_rows(tmp_path):
    recorder = RunRecorder(tmp_path, COLUMNS)
    try:
        for episode, theta in ((0, None), (1, THETA), (2, THETA)):
            recorder.record(episode_row(episode, theta), {"model_fit_s": 0.5, "policy_search_s": 1.5 + episode})
    finally:
        recorder.close()
    rows = read_csv(tmp_path / METRICS_FILE)
    assert list(rows[0]) == COLUMNS
    assert [r["return"] for r in rows] == ["0.5", "10.5", "20.5"]
    assert rows[0]["theta/out1/noise_variance"] == "" and float(rows[1]["theta/out1/noise_variance"]) == 2e-4
    assert theta_from_row(rows[2]).natural().equal(THETA.natural())  # metrics.csv keeps θ exactly
    assert [r["policy_search_s"] for r in read_csv(tmp_path / TIMINGS_FILE)] == ["1.5", "2.5", "3.5"]
    logged = scalars(tmp_path)
    assert logged["eval/return"] == [(0, 0.5), (1, 10.5), (2, 20.5)]
    assert logged["eval/success"] == [(0, 0.0), (1, 0.0), (2, 1.0)]
    assert logged["time/policy_search_s"] == [(0, 1.5), (1, 2.5), (2, 3.5)]
    assert logged["theta/out0/lengthscale/in1"] == [(1, 0.25), (2, 0.25)]  # none for the model-less episode
    assert "transfer/compliance" not in logged  # empty values are not logged

    resumed = RunRecorder(tmp_path, COLUMNS, Records(rows=[episode_row(0, None), episode_row(1, THETA)],
                                                     timings=read_csv(tmp_path / TIMINGS_FILE)[:2]))
    try:
        resumed.record(episode_row(2, THETA), {"model_fit_s": 0.5, "policy_search_s": 9.0})
    finally:
        resumed.close()
    assert [r["return"] for r in read_csv(tmp_path / METRICS_FILE)] == ["0.5", "10.5", "20.5"]
    assert [r["policy_search_s"] for r in read_csv(tmp_path / TIMINGS_FILE)] == ["1.5", "2.5", "9.0"]
    assert scalars(tmp_path)["time/policy_search_s"][-1] == (2, 9.0)  # the interrupted writer's step 2 purged


def test_trajectory_figure_labels_panels_with_state_names():
    steps = np.linspace(0.0, 1.0, 6)
    mean = np.stack([steps, -steps], axis=1)
    std, real = 0.1 * np.ones_like(mean), mean[:4] + 0.05
    fig = trajectory_figure(mean, std, real, "episode 3")
    assert [ax.get_ylabel() for ax in fig.axes] == ["x[0]", "x[1]"]
    named = trajectory_figure(mean, std, real, "episode 3", state_names=["cart position", "cart velocity"])
    assert [ax.get_ylabel() for ax in named.axes] == ["cart position", "cart velocity"]
    assert named.axes[0].get_title() == "episode 3"
    with pytest.raises(ValueError, match="1 state names for 2 state dimensions"):
        trajectory_figure(mean, std, real, "episode 3", state_names=["x"])
    plt.close(fig)
    plt.close(named)


def test_a_figure_reaches_tensorboard_as_an_image_at_its_episode(tmp_path):
    mean = np.stack([np.linspace(0.0, 1.0, 6)] * 2, axis=1)
    fig = trajectory_figure(mean, 0.1 * np.ones_like(mean), mean[:4], "episode 1")
    recorder = RunRecorder(tmp_path, COLUMNS)
    try:
        recorder.record(episode_row(0, None), {"model_fit_s": 0.0, "policy_search_s": 0.0})
        recorder.record(episode_row(1, THETA), {"model_fit_s": 0.5, "policy_search_s": 1.5}, fig)
    finally:
        recorder.close()
    events = EventAccumulator(str(tmp_path))
    events.Reload()
    assert events.Tags()["images"] == ["rollout/predicted_vs_real"]
    (image,) = events.Images("rollout/predicted_vs_real")
    assert image.step == 1 and image.width > 100 and image.height > 100
    assert not plt.fignum_exists(fig.number)  # closed once written


def test_a_run_loads_matplotlib_only_to_draw_a_figure():
    """The CLI's start (and its one-line user errors) skips matplotlib's ~0.7 s import; the first figure loads it."""
    code = ("import sys, numpy as np, qtl.train, qtl.loop; print('matplotlib' in sys.modules); "
            "from qtl.recorder import trajectory_figure; m = np.zeros((3, 1)); "
            "trajectory_figure(m, m, m, 't'); print('matplotlib' in sys.modules)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["False", "True"]


def test_env_return_and_an_estimated_start_reach_metrics_and_tensorboard_and_old_rows_still_write(tmp_path):
    columns = COLUMNS + start_columns(2)
    assert start_columns(2) == ["start/mean/0", "start/mean/1", "start/std/0", "start/std/1"]
    assert list(start_row(np.array([3.1, 0.0]), np.array([0.05, 0.01]))) == start_columns(2)
    old = episode_row(0, None)  # as rows of runs made before env_return: no such key
    recorder = RunRecorder(tmp_path, columns, Records(rows=[old]))
    try:
        row = {**episode_row(1, THETA), "env_return": -12.25, **start_row(np.array([3.1, 0.0]), np.array([0.05, 0.01]))}
        recorder.record(row, {"model_fit_s": 0.5, "policy_search_s": 1.0})
    finally:
        recorder.close()
    rows = read_csv(tmp_path / METRICS_FILE)
    assert [r["env_return"] for r in rows] == ["", "-12.25"]
    assert rows[1]["start/mean/0"] == "3.1" and rows[1]["start/std/1"] == "0.01" and rows[0]["start/std/1"] == ""
    logged = scalars(tmp_path)
    assert logged["eval/env_return"] == [(1, -12.25)]
    assert logged["start/mean/0"] == [(1, pytest.approx(3.1))] and logged["start/std/0"] == [(1, pytest.approx(0.05))]


def test_a_resumed_recorder_with_nothing_to_record_writes_no_events_file(tmp_path):
    recorder = RunRecorder(tmp_path, COLUMNS)
    try:
        recorder.record(episode_row(0, None), {"model_fit_s": 0.0, "policy_search_s": 0.0})
    finally:
        recorder.close()
    events = sorted(tmp_path.glob("events.out.tfevents*"))
    assert len(events) == 1
    finished = RunRecorder(tmp_path, COLUMNS, Records(rows=read_csv(tmp_path / METRICS_FILE),  # a sweep resuming
                                                      timings=read_csv(tmp_path / TIMINGS_FILE)))  # a finished run
    finished.close()
    assert sorted(tmp_path.glob("events.out.tfevents*")) == events
    assert scalars(tmp_path)["eval/return"] == [(0, 0.5)]
