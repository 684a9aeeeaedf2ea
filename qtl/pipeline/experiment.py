"""qtl-experiment: one of the paper's experiments end to end: source sweep, then target sweep, then the report.

    qtl-experiment cartpole|mountaincar|aircraft [--quick] [--status] [override ...]

Stage 1 runs ``qtl-train experiment=<name>_source`` (one source run per seed), stage 2
``qtl-train experiment=<name>`` (every approach x target x seed, each reading the source run of
its seed): two sweeps, so no target starts before its source exists. Both are Hydra multiruns on
the preset's launcher (``hydra/launcher=local``: joblib, one torch thread per job; ``slurm`` and
``ray`` presets exist for clusters). Presets set ``resume=auto``, so a repeated command continues
its runs instead of redoing them. ``--quick`` uses the reduced presets (``<name>_quick``: 2 seeds,
5 episodes, PILCO vs QTL Bayesian). Then, for the helicopter (the aircraft experiment), the
autopilot's total reward is recorded in ``<root>/experiment.yaml`` as the reference line of Fig. 3,
and ``qtl.report`` writes ``<root>/report/``.
Extra arguments are Hydra overrides for both sweeps (e.g. ``sweep.root=... hydra.launcher.n_jobs=4``).
``--status`` runs nothing: it prints, per stage, every run the sweep plans and the episodes each has made
(a finished sweep kept without its checkpoints, as ``docs/experiments/`` keeps it, by its ``metrics.csv``).
``experiment.yaml`` records the commands (``qtl-train ...``) with an absolute path in an override (``sweep.root=...``)
relative to the repository, from whose top the commands are run. A sweep root whose runs are kept without their
checkpoints (a finished sweep in git, ``docs/experiments/README.md``) is refused: resuming needs them, and a fresh
start would overwrite the kept files; rerun it into another ``sweep.root``.
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from hydra import compose, initialize_config_module
from hydra.errors import HydraException
from omegaconf.errors import OmegaConfBaseException

from qtl.checkpoint import episodes_done
from qtl.config import register_configs
from qtl.errors import UserError
from qtl.launch import planned_runs
from qtl.report import EXPERIMENT_FILE, REPORT_DIR, ExperimentRecord, record_reference, write_report
from qtl.report.paths import recorded_override
from qtl.report.progress import PlannedRun, episodes_made, progress_markdown, sweep_progress
from qtl.train import one_line

PROG = "qtl-experiment"
EXPERIMENTS = ("cartpole", "mountaincar", "aircraft")
STAGES = 2  # the source sweep, then the target sweep


def sweep_root(preset: str, overrides: list[str]) -> Path:
    """Where the preset (with the overrides) puts its runs: ``sweep.root``."""
    register_configs()
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"experiment={preset}", *overrides])
    return Path(cfg.sweep.root)


def kept_without_checkpoints(runs: list[PlannedRun]) -> list[Path]:
    """The runs that have made episodes (their ``metrics.csv``) but hold no checkpoint to resume them from."""
    return [run.run_dir for run in runs if not episodes_done(run.run_dir) and episodes_made(run.run_dir)]


def parser() -> argparse.ArgumentParser:
    """The command line of ``qtl-experiment``: the experiment, its options, then Hydra overrides."""
    found = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    found.add_argument("experiment", choices=EXPERIMENTS)
    found.add_argument("--quick", action="store_true", help="the reduced preset (2 seeds, 5 episodes)")
    found.add_argument("--status", action="store_true",
                       help="run nothing: print every planned run and the episodes it has made")
    return found


def stages(name: str) -> list[str]:
    """The presets of the two sweeps, in order: the sources, then the targets."""
    return [f"{name}_source", name]


def main(argv: Sequence[str] | None = None) -> None:
    """Record the experiment, run both sweeps, record the reference line, write the report."""
    cli = parser()
    args, overrides = cli.parse_known_args(argv)
    if unknown := [token for token in overrides if token.startswith("-")]:
        cli.error(f"unrecognised option(s) {' '.join(unknown)}: see --help (Hydra overrides are key=value)")
    name = f"{args.experiment}_quick" if args.quick else args.experiment
    try:  # a bad override stops here, in one line, before anything runs
        root = sweep_root(name, [o for o in overrides if not o.startswith("hydra.")])
        planned = {f"{stage} ({preset})": planned_runs(preset, overrides)
                   for stage, preset in zip(("sources", "targets"), stages(name), strict=True)}
    except (UserError, HydraException, OmegaConfBaseException) as err:
        cli.error(one_line(err))
    if args.status:
        progress = {stage: sweep_progress(runs) for stage, runs in planned.items()}
        print(f"{root}\n\n{progress_markdown(progress, root)}", end="")
        return
    if kept := kept_without_checkpoints([run for runs in planned.values() for run in runs]):
        cli.exit(1, f"{cli.prog}: {len(kept)} run(s) under {root} are kept without their checkpoints (e.g. "
                    f"{kept[0].relative_to(root) if kept[0].is_relative_to(root) else kept[0]}), so they can be "
                    "neither resumed nor restarted there without losing their files: rerun the sweep into another "
                    "sweep.root (docs/experiments/README.md)\n")
    commands = [[sys.executable, "-m", "qtl", f"experiment={preset}", *overrides] for preset in stages(name)]
    root.mkdir(parents=True, exist_ok=True)
    shown = [shlex.join(["qtl-train", *map(recorded_override, c[3:])]) for c in commands]
    ExperimentRecord(name=args.experiment, commands=shown).write(root)
    for stage, (command, line) in enumerate(zip(commands, shown, strict=True), start=1):
        print(f"[{stage}/{STAGES}] {line}", flush=True)
        tic = time.perf_counter()
        subprocess.run(command, check=True)
        print(f"[{stage}/{STAGES}] done in {time.perf_counter() - tic:.0f} s", flush=True)
    reference = record_reference(root)
    if reference is not None:
        print(f"reference: {reference.name} total reward {reference.total:.2f} (in {root / EXPERIMENT_FILE})")
    print(f"report: {write_report(root, root / REPORT_DIR)}")


if __name__ == "__main__":
    main()
