"""Research — how well a run's real transitions follow its task's declared kinematics: the integrated positions' error.

For each run directory given (its newest checkpoint's dataset: every real tuple (x_t, u_t, Δ_t)), the residual of
speed integration's position, Δq − (T q̇_t + w T Δq̇_t), per declared position, with the task's ``kinematics``
(or ``--period``/``--weight`` instead): its median, 99th percentile and largest absolute value, beside the spread
of Δq itself. Large residuals on some tuples say where the system's positions do not follow their velocities (the
mountain car's right end clips x and keeps v). Prints Markdown; writes nothing.

    python scripts/research/kinematic_residual.py runs/bench_kinematic/mountaincar-delta/seed_0 [RUN ...]
        [--period T] [--weight W]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from qtl.bench import display_path, markdown_table
from qtl.runs import load_run


def residuals(run_dir: Path, period: float | None, weight: float | None) -> list[list[str]]:
    """One table row per declared position of the run's task: its residual statistics."""
    run = load_run(run_dir, overrides=["propagation.integration=speed"])
    kinematics = run.parts.task.kinematics
    if kinematics is None:
        raise SystemExit(f"{display_path(run_dir)}: its task declares no kinematics")
    period = kinematics.period if period is None else period
    weight = kinematics.weight if weight is None else weight
    x, _, delta = run.dataset().tensors(torch.float64, "cpu")
    rows = []
    for p, v in zip(kinematics.positions, kinematics.velocities, strict=True):
        error = (delta[:, p] - (period * x[:, v] + weight * period * delta[:, v])).abs()
        rows.append([display_path(run_dir), p, len(error), f"{period:g}", f"{weight:g}", f"{error.median():.4f}",
                     f"{error.quantile(0.99):.4f}", f"{error.max():.4f}", f"{delta[:, p].abs().median():.4f}"])
    return rows


def main() -> None:
    """Print the residual table of every run given."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+", help="run directories (their newest checkpoints are read)")
    parser.add_argument("--period", type=float, help="T instead of the task's")
    parser.add_argument("--weight", type=float, help="w instead of the task's")
    args = parser.parse_args()
    rows = [row for run in args.runs for row in residuals(run, args.period, args.weight)]
    print(markdown_table(rows, ["run", "position", "tuples", "T", "w", "median |residual|", "99th percentile",
                                "max", "median |Δq|"], "lrrrrrrrr"))


if __name__ == "__main__":
    main()
