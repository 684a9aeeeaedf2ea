"""Learning runs as subprocesses of the real CLI, reused when finished and resumed when interrupted."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import yaml

from qtl.checkpoint import CHECKPOINT_DIR

# Overrides that do not change what a run computes.
NEUTRAL_OVERRIDES = ("hydra.run.dir=", "progress=", "threads=")


class RunMismatch(RuntimeError):
    """A run directory exists but was made by other overrides."""


def effective(overrides: list[str]) -> list[str]:
    """The overrides that change a run's results, sorted."""
    return sorted(o for o in overrides if not o.startswith(NEUTRAL_OVERRIDES))


def ensure_run(overrides: list[str], run_dir: Path, episodes: int, *, threads: int = 1) -> float:
    """Make ``run_dir`` a finished run of ``overrides`` with ``episodes`` episodes in all; seconds spent here.

    A finished run made by the same overrides is reused (same config, same seed: the same run),
    an interrupted one is resumed from its last checkpoint, any other run in the way is an error.
    """
    made_with = run_dir / ".hydra" / "overrides.yaml"
    if made_with.exists():
        found = effective(yaml.safe_load(made_with.read_text()))
        if found != effective(overrides):
            raise RunMismatch(f"{run_dir} was made with other overrides:\n  {found}\nnot\n  {effective(overrides)}")
    checkpoints = sorted((run_dir / CHECKPOINT_DIR).glob("episode_*.pt")) if run_dir.exists() else []
    if len(checkpoints) >= episodes:
        return 0.0
    if checkpoints:
        args = [f"resume={run_dir}", "progress=false", f"threads={threads}"]
    else:
        args = [*overrides, "progress=false", f"threads={threads}", f"hydra.run.dir={run_dir}"]
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "qtl", *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"run {run_dir} failed:\n{done.stderr[-3000:]}")
    return time.perf_counter() - start
