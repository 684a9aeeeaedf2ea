"""Learning runs as subprocesses of the real CLI, reused when finished and resumed when interrupted; a sweep's runs."""

from __future__ import annotations

import itertools
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import yaml
from hydra import compose, initialize_config_module
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import DictConfig, OmegaConf

from qtl.checkpoint import episodes_done
from qtl.config import register_configs
from qtl.errors import RunMismatch, UserError
from qtl.report.progress import PlannedRun

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
            HydraConfig.instance().set_config(cfg)  # `${hydra:runtime.choices.*}` in subdir reads it
            run_dir = Path(str(cfg.hydra.sweep.dir)) / str(cfg.hydra.sweep.subdir)
            runs.append(PlannedRun(run_dir=run_dir, overrides=tuple(combo), episodes=int(cfg.episodes) + 1))
    return runs
