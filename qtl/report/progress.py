"""Where a sweep stands: every run its preset plans, with the episodes each has made so far.

A full-scale sweep outlasts a working session, and its runs are continued by repeating the command
(``resume=auto``). ``planned_runs`` expands a preset's ``hydra.sweeper.params`` (with the command
line's overrides, which replace or fix a swept key as they would in the multirun) into the run
directories Hydra gives them; ``sweep_progress`` reads what each has checkpointed and the time
its episodes took (``timings.csv``), and ``progress_markdown`` puts it in a table.
"""

from __future__ import annotations

import csv
import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
from hydra import compose, initialize_config_module
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import DictConfig, OmegaConf

from qtl.checkpoint import episodes_done
from qtl.config import register_configs
from qtl.errors import UserError
from qtl.recorder import TIMINGS_FILE
from qtl.report.tables import markdown


@dataclass(frozen=True)
class PlannedRun:
    """One job of a sweep: its run directory, its swept overrides and the episodes it is to make (initial included)."""

    run_dir: Path
    overrides: tuple[str, ...]
    episodes: int


@dataclass(frozen=True)
class RunProgress:
    """A planned run as found on disk: episodes checkpointed and the seconds its recorded episodes took."""

    run: PlannedRun
    done: int
    seconds: float

    @property
    def finished(self) -> bool:
        """Whether the run has made every episode it plans."""
        return self.done >= self.run.episodes


def _sweep_params(cfg: DictConfig, overrides: Sequence[str]) -> dict[str, str]:
    """The preset's swept keys and values, with the command line's overrides of the same keys (or new sweeps) in."""
    params = {str(k): str(v) for k, v in (cfg.hydra.sweeper.params or {}).items()}
    parser = OverridesParser.create()
    for text in overrides:
        override = parser.parse_override(text)
        key = override.get_key_element()
        if override.is_sweep_override() or key in params:
            params[key] = text.split("=", 1)[1]
    return params


def planned_runs(preset: str, overrides: Sequence[str] = ()) -> list[PlannedRun]:
    """Every run of the multirun ``qtl-train experiment=<preset> <overrides>``, in the sweeper's order.

    Config-group choices (e.g. ``approach``) are composed once per combination, plain values (``seed``,
    ``task.env.pole_mass``) set on that config, and ``hydra.sweep.dir/subdir`` resolved as Hydra does.
    """
    register_configs()
    hydra_config = HydraConfig.instance()
    previous = hydra_config.cfg  # resolving `${hydra:...}` sets Hydra's global config: restored below
    try:
        return _planned_runs(preset, overrides)
    finally:
        hydra_config.cfg = previous


def _planned_runs(preset: str, overrides: Sequence[str]) -> list[PlannedRun]:
    """``planned_runs``, Hydra's global config left set to the last run's."""
    parser = OverridesParser.create()
    fixed = [o for o in overrides if not parser.parse_override(o).is_sweep_override()]
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        base = compose(config_name="train", overrides=[f"experiment={preset}", *fixed], return_hydra_config=True)
        params = _sweep_params(base, overrides)
        if not params:
            raise UserError(f"experiment={preset} sweeps nothing (no hydra.sweeper.params): it is a single run")
        groups = set(base.hydra.runtime.choices)
        swept = []  # per swept key, its overrides in the sweeper's order
        for key, value in params.items():
            override = parser.parse_override(f"{key}={value}")
            values = list(override.sweep_string_iterator()) if override.is_sweep_override() else [value]
            swept.append([f"{key}={v}" for v in values])
        composed: dict[tuple[str, ...], DictConfig] = {}
        runs = []
        for combo in itertools.product(*swept):
            chosen = tuple(o for o in combo if o.split("=", 1)[0] in groups)
            if chosen not in composed:
                composed[chosen] = compose(config_name="train",
                                           overrides=[f"experiment={preset}", *fixed, *chosen],
                                           return_hydra_config=True)
            cfg = composed[chosen].copy()
            for override in combo:
                if override not in chosen:
                    key = override.split("=", 1)[0]
                    OmegaConf.update(cfg, key, parser.parse_override(override).value(), force_add=True)
            HydraConfig.instance().set_config(cfg)
            run_dir = Path(str(cfg.hydra.sweep.dir)) / str(cfg.hydra.sweep.subdir)
            runs.append(PlannedRun(run_dir=run_dir, overrides=tuple(combo), episodes=int(cfg.episodes) + 1))
    return runs


def _recorded_seconds(run_dir: Path, episodes: int) -> float:
    """Seconds the run's first ``episodes`` recorded episodes took (``timings.csv``'s ``episode_s``)."""
    path = run_dir / TIMINGS_FILE
    if not path.is_file():
        return 0.0
    with open(path, newline="") as f:
        rows = [row for row in csv.DictReader(f) if row.get("episode_s")]
    return sum(float(row["episode_s"]) for row in rows[:episodes])


def sweep_progress(runs: Sequence[PlannedRun]) -> list[RunProgress]:
    """What each planned run has made so far (0 episodes for a run not begun)."""
    found = []
    for run in runs:
        done = min(episodes_done(run.run_dir), run.episodes) if run.run_dir.is_dir() else 0
        found.append(RunProgress(run=run, done=done, seconds=_recorded_seconds(run.run_dir, done)))
    return found


def progress_markdown(stages: dict[str, list[RunProgress]], root: Path | None = None) -> str:
    """Per stage a summary line and a table: run, episodes made / planned, hours its episodes took."""
    blocks = []
    for stage, progress in stages.items():
        made = sum(p.done for p in progress)
        planned = sum(p.run.episodes for p in progress)
        begun = sum(p.done > 0 for p in progress)
        finished = sum(p.finished for p in progress)
        hours = sum(p.seconds for p in progress) / 3600
        rows = [[str(p.run.run_dir.relative_to(root) if root and p.run.run_dir.is_relative_to(root)
                     else p.run.run_dir), f"{p.done} / {p.run.episodes}",
                 "done" if p.finished else ("begun" if p.done else "not begun"), f"{p.seconds / 3600:.2f}"]
                for p in progress]
        blocks.append(
            f"**{stage}**: {finished} of {len(progress)} runs finished, {begun - finished} begun, "
            f"{len(progress) - begun} not begun; {made} of {planned} episodes made ({hours:.1f} h recorded)\n\n"
            + markdown(pd.DataFrame(rows, columns=["run", "episodes", "state", "hours"]), text_columns=3)
        )
    return "\n\n".join(blocks) + "\n"
