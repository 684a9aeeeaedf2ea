"""Learning runs as subprocesses of the real CLI, reused when finished and resumed when interrupted."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import yaml

from qtl.checkpoint import episodes_done
from qtl.errors import RunMismatch

# Overrides that do not change what a run computes (``episodes`` only says how far it goes: runs
# are causal, so a run extended by resuming equals one made longer from the start; ``resume`` and
# ``keep_checkpoints`` say how it is continued and stored, not what it learns).
NEUTRAL_OVERRIDES = ("hydra.run.dir=", "progress=", "threads=", "episodes=", "resume=", "keep_checkpoints=")



def effective(overrides: list[str]) -> list[str]:
    """The overrides that change a run's results, sorted (a ``--`` separator, which Hydra never records, dropped)."""
    return sorted(o for o in overrides if o != "--" and not o.startswith(NEUTRAL_OVERRIDES))


def ensure_run(overrides: list[str], run_dir: Path, episodes: int, *, threads: int = 1) -> float:
    """Make ``run_dir`` a run of ``overrides`` with at least ``episodes`` episodes in all; seconds spent here.

    A run made by the same overrides is reused (same config, same seed: the same run) and, when
    interrupted or shorter, resumed from its last checkpoint up to the ``episodes=`` of
    ``overrides``; a run made by other overrides is an error.
    """
    made_with = run_dir / ".hydra" / "overrides.yaml"
    if made_with.exists():
        found = effective(yaml.safe_load(made_with.read_text()))
        if found != effective(overrides):
            raise RunMismatch(f"{run_dir} was made with other overrides:\n  {found}\nnot\n  {effective(overrides)}")
    made = episodes_done(run_dir)
    if made >= episodes:
        return 0.0
    if made:
        extend = [o for o in overrides if o.startswith("episodes=")]
        # A resumed run logs into its own directory (qtl-train's default for resume=).
        args = [f"resume={run_dir}", *extend, "progress=false", f"threads={threads}"]
    else:
        args = [*overrides, "progress=false", f"threads={threads}", f"hydra.run.dir={run_dir}"]
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "qtl", *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"run {run_dir} failed:\n{done.stderr[-3000:]}")
    return time.perf_counter() - start
