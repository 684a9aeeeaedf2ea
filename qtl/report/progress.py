"""Where a sweep stands: every run it plans, with the episodes each has made so far.

A full-scale sweep outlasts a working session, and its runs are continued by repeating the command
(``resume=auto``). Given the runs a sweep plans (``qtl.launch.planned_runs`` expands a preset's
Hydra sweep into them), ``sweep_progress`` reads what each has made (its checkpoints; a finished run kept
without them, as ``docs/experiments/`` keeps it, by its ``metrics.csv``) and the time its episodes took
(``timings.csv``), ``remaining_hours`` prices the episodes still to make at the finished runs'
pace, and ``progress_markdown`` puts it in a table.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from qtl.checkpoint import episodes_done
from qtl.recorder import METRICS_FILE, TIMINGS_FILE
from qtl.report.tables import markdown


@dataclass(frozen=True)
class PlannedRun:
    """One job of a sweep: its run directory, its swept overrides and the episodes it is to make (initial included)."""

    run_dir: Path
    overrides: tuple[str, ...]
    episodes: int


@dataclass(frozen=True)
class RunProgress:
    """A planned run as found on disk: episodes made and the seconds each recorded episode took."""

    run: PlannedRun
    done: int
    episode_seconds: tuple[float, ...]  # of the first ``done`` episodes, as far as ``timings.csv`` records them

    @property
    def seconds(self) -> float:
        """Seconds its recorded episodes took."""
        return sum(self.episode_seconds)

    @property
    def finished(self) -> bool:
        """Whether the run has made every episode it plans."""
        return self.done >= self.run.episodes


def _recorded_seconds(run_dir: Path, episodes: int) -> tuple[float, ...]:
    """Seconds each of the run's first ``episodes`` recorded episodes took (``timings.csv``'s ``episode_s``)."""
    path = run_dir / TIMINGS_FILE
    if not path.is_file():
        return ()
    with open(path, newline="") as f:
        rows = [row for row in csv.DictReader(f) if row.get("episode_s")]
    return tuple(float(row["episode_s"]) for row in rows[:episodes])


def episodes_made(run_dir: Path) -> int:
    """Episodes a run has made: those checkpointed (what a resume continues from), or, in a run kept without its
    checkpoints (a finished sweep in git), the rows of its ``metrics.csv``; 0 where neither exists."""
    checkpointed = episodes_done(run_dir)  # 0 where the directory does not exist yet
    if checkpointed:
        return checkpointed
    path = run_dir / METRICS_FILE
    if not path.is_file():
        return 0
    with open(path, newline="") as f:
        return sum(1 for _ in csv.DictReader(f))


def sweep_progress(runs: Sequence[PlannedRun]) -> list[RunProgress]:
    """What each planned run has made so far (0 episodes for a run not begun)."""
    found = []
    for run in runs:
        done = min(episodes_made(run.run_dir), run.episodes)
        found.append(RunProgress(run=run, done=done, episode_seconds=_recorded_seconds(run.run_dir, done)))
    return found


def remaining_hours(progress: Sequence[RunProgress]) -> float | None:
    """Hours of one core the episodes still to make need, each at the finished runs' mean time for that episode
    (later episodes fit and search on more data); None before a run has finished with all its times recorded."""
    complete = [p.episode_seconds for p in progress if p.finished and len(p.episode_seconds) == p.done]
    if not complete:
        return None
    longest = max(map(len, complete))
    per_episode = [sum(run[e] for run in complete if e < len(run)) / sum(e < len(run) for run in complete)
                   for e in range(longest)]
    # An episode past the longest finished run's is taken at that run's last episode's time.
    return sum(per_episode[min(e, longest - 1)] for p in progress if not p.finished
               for e in range(p.done, p.run.episodes)) / 3600


def progress_markdown(stages: dict[str, list[RunProgress]], root: Path | None = None) -> str:
    """Per stage a summary line and a table: run, episodes made / planned, hours its episodes took."""
    blocks = []
    for stage, progress in stages.items():
        made = sum(p.done for p in progress)
        planned = sum(p.run.episodes for p in progress)
        begun = sum(p.done > 0 for p in progress)
        finished = sum(p.finished for p in progress)
        hours = sum(p.seconds for p in progress) / 3600
        left = remaining_hours(progress)
        pace = ("" if finished == len(progress) or left is None else
                f"; ~{left:.1f} h of one core to go at the finished runs' time per episode")
        rows = [[str(p.run.run_dir.relative_to(root) if root and p.run.run_dir.is_relative_to(root)
                     else p.run.run_dir), f"{p.done} / {p.run.episodes}",
                 "done" if p.finished else ("begun" if p.done else "not begun"), f"{p.seconds / 3600:.2f}"]
                for p in progress]
        blocks.append(
            f"**{stage}**: {finished} of {len(progress)} runs finished, {begun - finished} begun, "
            f"{len(progress) - begun} not begun; {made} of {planned} episodes made ({hours:.1f} h recorded{pace})\n\n"
            + markdown(pd.DataFrame(rows, columns=["run", "episodes", "state", "hours"]), text_columns=3)
        )
    return "\n\n".join(blocks) + "\n"
