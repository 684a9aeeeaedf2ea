"""What a run writes as it learns: TensorBoard scalars, figures and videos, and ``metrics.csv``."""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from torch.utils.tensorboard import SummaryWriter

from qtl.constraints import Constraint
from qtl.health import EVENTS
from qtl.models import GPHyperparameters
from qtl.transfer.plan import SELECTED_SOURCE, SOURCE_COMPLIANCE_PREFIX
from qtl.transfer.samples import SAMPLE_COLUMNS
from qtl.video import Clip, video_summary

if TYPE_CHECKING:  # matplotlib loads only where a figure is drawn (~0.7 s off every CLI start)
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

FIGURE_TAG = "rollout/predicted_vs_real"  # the predicted-vs-real figure of an episode (``figure_every``)
VIDEO_TAG = "rollout/video"  # the same episode on the real system, rendered (``video``)
METRICS_FILE = "metrics.csv"  # the one spelling: qtl.metrics, qtl.report and the scripts import it
THETA_PREFIX = "theta"  # θ_i, what the episode's model used
THETA_P_PREFIX = "theta_p"  # θ_p_i, what evidence maximisation found
START_PREFIX = "start"  # μ_0, σ_0 estimated from the episodes' initial states (tasks with no start distribution)
# Wall times differ between identical runs, so they live apart from metrics.csv (which same seed
# reproduces exactly).
TIMINGS_FILE = "timings.csv"
TIMING_COLUMNS = ["episode", "model_fit_s", "policy_search_s", "episode_s"]  # episode_s: the whole episode
# Numerical trouble per episode (qtl.health's counts) and whether the episode began a resumed session.
HEALTH_FILE = "health.csv"
HEALTH_COLUMNS = ["episode", "resumed", *EVENTS]
# Of a panel's range, how much of a shaded region beyond a bound stays in view (the prediction figure's constraints).
BOUND_MARGIN = 0.1
BASE_COLUMNS = [
    "episode",
    "kind",
    "return",
    "env_return",  # the env's own reward summed (logged only: the task's saturating reward is what is learned)
    "predicted_return",
    "success",
    "length",
    "final_distance",
    "model_smse",
    "model_log_evidence",
    "policy_evaluations",
    "compliance",  # task compliance Λ (Eq. 14) of the tuples the episode's model learned from
    "fallback",  # 1 once the compliance gate has switched the run to PILCO
    "predicted_survival",  # S_H of the prediction under the task's terminate constraints (1: none; qtl.constraints)
    "survival_half_step",  # the first step t with S_t < 0.5 (empty: never)
    "crossed",  # 1 if the real episode's states left a declared bound (any kind), else 0
]


def theta_columns(num_outputs: int, input_dim: int, prefix: str = THETA_PREFIX,
                  outputs: Sequence[int] | None = None) -> list[str]:
    """``<prefix>/out{d}/lengthscale/in{i}``, ``…/signal_variance``, ``…/noise_variance`` column names.

    ``theta``: θ_i, what the episode's model used; ``theta_p``: θ_p_i, what evidence maximisation found.
    ``outputs``: the state dimension d each output models (default 0..E−1).
    """
    return [f"{prefix}/{key}" for key in GPHyperparameters.keys(num_outputs, input_dim, outputs)]


def start_columns(state_dim: int) -> list[str]:
    """``start/mean/{i}`` and ``start/std/{i}`` column names of an estimated start distribution `D`."""
    return [f"{START_PREFIX}/{what}/{i}" for what in ("mean", "std") for i in range(state_dim)]


def start_row(mean: np.ndarray, std: np.ndarray) -> dict[str, float]:
    """μ_0 `D` and σ_0 `D` as ``{column: value}`` (the names of :func:`start_columns`)."""
    return {**{f"{START_PREFIX}/mean/{i}": float(m) for i, m in enumerate(mean)},
            **{f"{START_PREFIX}/std/{i}": float(s) for i, s in enumerate(std)}}


def theta_row(theta: GPHyperparameters | None, prefix: str = THETA_PREFIX,
              outputs: Sequence[int] | None = None) -> dict[str, float]:
    """θ as ``{column: value}`` (empty when there is no model yet); ``outputs`` as :func:`theta_columns`."""
    return {} if theta is None else {f"{prefix}/{k}": v for k, v in theta.as_dict(outputs).items()}


def theta_from_row(row: Mapping[str, float | str], prefix: str = THETA_PREFIX) -> GPHyperparameters | None:
    """θ back from a metrics row's ``<prefix>/…`` columns (the inverse of :func:`theta_row`); None if they are empty.

    ``row`` is a row as recorded (floats) or as read back from ``metrics.csv`` (strings, empty where no model).
    """
    start = f"{prefix}/"
    values = {k: v for k, v in row.items() if k.startswith(start) and v not in (None, "")}
    return GPHyperparameters.from_dict(values, start) if values else None


@dataclass
class Records:
    """A run's records so far, a dict per episode: the rows of ``metrics.csv``, ``timings.csv``, ``health.csv``."""

    rows: list[dict[str, Any]] = field(default_factory=list)
    timings: list[dict[str, Any]] = field(default_factory=list)
    health: list[dict[str, Any]] = field(default_factory=list)


class RunRecorder:
    """Writes one row per episode to ``metrics.csv`` (and ``timings.csv``, ``health.csv``) and to TensorBoard.

    ``records``: the run's records, appended to as episodes are recorded; when resuming, they hold the
    earlier episodes' rows: the CSV files are rewritten with exactly them, and TensorBoard events from step
    ``len(records.rows)`` on, left by an interrupted writer, are purged.
    """

    def __init__(self, output_dir: Path, columns: Sequence[str], records: Records | None = None) -> None:
        self.output_dir = Path(output_dir)
        self.columns = list(columns)
        self.records = Records() if records is None else records
        self._purge_step = len(self.records.rows) if self.records.rows else None
        self._writer: SummaryWriter | None = None
        self.output_dir.mkdir(parents=True, exist_ok=True)
        _write_csv(self.output_dir / METRICS_FILE, self.columns, self.records.rows)
        _write_csv(self.output_dir / TIMINGS_FILE, TIMING_COLUMNS, self.records.timings)
        _write_csv(self.output_dir / HEALTH_FILE, HEALTH_COLUMNS, self.records.health)

    @property
    def writer(self) -> SummaryWriter:
        """The TensorBoard writer, opened at first use: resuming a finished run leaves no empty events file."""
        if self._writer is None:
            self._writer = SummaryWriter(log_dir=str(self.output_dir), purge_step=self._purge_step)
        return self._writer

    def record(
        self,
        row: dict[str, Any],
        timings: dict[str, float],
        figure: Figure | None = None,
        health: dict[str, int] | None = None,
        video: Clip | None = None,
    ) -> None:
        """Append an episode's row, timings and health counts; write scalars (figure, video) to TensorBoard; flush.

        The video is the summary TensorBoard's ``add_video`` writes (an animated GIF), encoded without moviepy.
        """
        step = int(row["episode"])
        timings = {"episode": step, **timings}
        health = {"episode": step, "resumed": 0, **{event: 0 for event in EVENTS}, **(health or {})}
        _append_csv(self.output_dir / METRICS_FILE, self.columns, row)
        _append_csv(self.output_dir / TIMINGS_FILE, TIMING_COLUMNS, timings)
        _append_csv(self.output_dir / HEALTH_FILE, HEALTH_COLUMNS, health)
        self.records.rows.append(dict(row))
        self.records.timings.append(timings)
        self.records.health.append(health)
        tags = {
            "eval/return": row.get("return"),
            "eval/env_return": row.get("env_return"),
            "eval/success": row.get("success"),
            "eval/length": row.get("length"),
            "eval/final_distance": row.get("final_distance"),
            "policy/predicted_return": row.get("predicted_return"),
            "policy/evaluations": row.get("policy_evaluations"),
            "model/smse": row.get("model_smse"),
            "model/log_evidence": row.get("model_log_evidence"),
            "transfer/compliance": row.get("compliance"),
            "transfer/fallback": row.get("fallback"),
            "policy/predicted_survival": row.get("predicted_survival"),
            "policy/survival_half_step": row.get("survival_half_step"),
            "eval/crossed": row.get("crossed"),
            "time/model_fit_s": timings["model_fit_s"],
            "time/policy_search_s": timings["policy_search_s"],
            "time/episode_s": timings.get("episode_s"),
        }
        tags.update({k: v for k, v in row.items()
                     if k.startswith((f"{THETA_PREFIX}/", f"{THETA_P_PREFIX}/", f"{START_PREFIX}/"))})
        tags.update({f"transfer/{k}": v for k, v in row.items() if k.startswith(f"{SOURCE_COMPLIANCE_PREFIX}/")})
        if SELECTED_SOURCE in row:
            tags[f"transfer/{SELECTED_SOURCE}"] = row[SELECTED_SOURCE]
        tags.update({f"transfer/{k}": row[k] for k in SAMPLE_COLUMNS if k in row})  # transfer.samples=relevance
        tags.update({f"health/{event}": health[event] for event in EVENTS})
        for tag, value in tags.items():
            if value is not None and value != "" and math.isfinite(float(value)):
                self.writer.add_scalar(tag, float(value), step)
        if figure is not None:
            self.writer.add_figure(FIGURE_TAG, figure, step, close=True)
        if video is not None:  # what add_video does, through the same event file writer
            self.writer._get_file_writer().add_summary(video_summary(VIDEO_TAG, video), step)
        self.writer.flush()

    def close(self) -> None:
        """Flush and close the TensorBoard writer, if one was opened."""
        if self._writer is not None:
            self._writer.close()


def _write_csv(path: Path, columns: Sequence[str], rows: Sequence[dict[str, Any]]) -> None:
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)


def _append_csv(path: Path, columns: Sequence[str], row: dict[str, Any]) -> None:
    with open(path, "a", newline="") as f:
        csv.DictWriter(f, fieldnames=columns, extrasaction="ignore").writerow(row)


def trajectory_figure(
    predicted_mean: np.ndarray,
    predicted_std: np.ndarray,
    real: np.ndarray,
    title: str,
    state_names: Sequence[str] | None = None,
    ended_at: int | None = None,
    ended_label: str = "terminated",
    constraints: Sequence[Constraint] = (),
) -> Figure:
    """Predicted mean ± 2 std `T+1 x D` against the real states `T'+1 x D`, one panel per dimension.

    ``state_names`` label the D panels (default ``x[0]`` … ``x[D-1]``). ``ended_at``: the step where
    the real episode ended before the horizon, marked by a vertical line "<ended_label> at step T".
    ``constraints``: the task's state bounds, the region outside each shaded in its dimension's panel.
    """
    dims = real.shape[1]
    if state_names is None:
        state_names = [f"x[{d}]" for d in range(dims)]
    elif len(state_names) != dims:
        raise ValueError(f"{len(state_names)} state names for {dims} state dimensions")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(dims, 1, figsize=(6, 1.8 * dims), sharex=True, squeeze=False)
    steps = np.arange(predicted_mean.shape[0])
    for d, ax in enumerate(axes[:, 0]):
        ax.fill_between(steps, predicted_mean[:, d] - 2 * predicted_std[:, d],
                        predicted_mean[:, d] + 2 * predicted_std[:, d], alpha=0.3, label="predicted ± 2σ")
        ax.plot(steps, predicted_mean[:, d], label="predicted mean")
        ax.plot(np.arange(real.shape[0]), real[:, d], "k.-", markersize=3, label="real")
        if ended_at is not None:
            ax.axvline(ended_at, color="tab:red", linestyle="--", linewidth=1,
                       label=f"{ended_label} at step {ended_at}")
        for c in (c for c in constraints if c.dim == d):
            _shade_outside(ax, c)
        ax.set_ylabel(state_names[d])
    axes[0, 0].set_title(title)
    axes[0, 0].legend(loc="best", fontsize="small")
    axes[-1, 0].set_xlabel("step")
    fig.tight_layout()
    return fig


def _shade_outside(ax: Axes, constraint: Constraint) -> None:
    """Shade the values beyond ``constraint``'s bounds (red: terminate, orange: penalty), the bounds kept in view."""
    color = "tab:red" if constraint.kind == "terminate" else "tab:orange"
    bounds = [b for b in (constraint.low, constraint.high) if b is not None]
    low, high = ax.get_ylim()
    margin = BOUND_MARGIN * (max(high, *bounds) - min(low, *bounds))
    low = min(low, constraint.low - margin) if constraint.low is not None else low
    high = max(high, constraint.high + margin) if constraint.high is not None else high
    label = f"outside bounds ({constraint.kind})"
    if constraint.low is not None:
        ax.axhspan(low, constraint.low, color=color, alpha=0.12, label=label)
        label = "_nolegend_"  # one legend entry per bound
    if constraint.high is not None:
        ax.axhspan(constraint.high, high, color=color, alpha=0.12, label=label)
    ax.set_ylim(low, high)
