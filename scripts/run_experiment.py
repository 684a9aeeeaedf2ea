"""Run one of the paper's experiments end to end: source sweep, then target sweep, then the report.

    python scripts/run_experiment.py cartpole|mountaincar|aircraft [--quick] [override ...]

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
``--status`` runs nothing: it prints, per stage, every run the sweep plans and the episodes each has made.
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
import time
from pathlib import Path

from hydra import compose, initialize_config_module

from qtl.config import register_configs
from qtl.launch import planned_runs
from qtl.report import EXPERIMENT_FILE, REPORT_DIR, ExperimentRecord, record_reference, write_report
from qtl.report.progress import progress_markdown, sweep_progress

EXPERIMENTS = ("cartpole", "mountaincar", "aircraft")


def sweep_root(preset: str, overrides: list[str]) -> Path:
    """Where the preset (with the overrides) puts its runs: ``sweep.root``."""
    register_configs()
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        cfg = compose(config_name="train", overrides=[f"experiment={preset}", *overrides])
    return Path(cfg.sweep.root)


def main() -> None:
    """Record the experiment, run both sweeps, record the reference line, write the report."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("experiment", choices=EXPERIMENTS)
    parser.add_argument("--quick", action="store_true", help="the reduced preset (2 seeds, 5 episodes)")
    parser.add_argument("--status", action="store_true",
                        help="run nothing: print every planned run and the episodes it has made")
    args, overrides = parser.parse_known_args()
    name = f"{args.experiment}_quick" if args.quick else args.experiment
    root = sweep_root(name, [o for o in overrides if not o.startswith("hydra.")])
    if args.status:
        stages = {f"{stage} ({preset})": sweep_progress(planned_runs(preset, overrides))
                  for stage, preset in (("sources", f"{name}_source"), ("targets", name))}
        print(f"{root}\n\n{progress_markdown(stages, root)}", end="")
        return
    commands = [[sys.executable, "-m", "qtl", f"experiment={preset}", *overrides] for preset in
                (f"{name}_source", name)]
    root.mkdir(parents=True, exist_ok=True)
    shown = [shlex.join(["qtl-train", *c[3:]]) for c in commands]
    ExperimentRecord(name=args.experiment, commands=shown).write(root)
    for stage, (command, line) in enumerate(zip(commands, shown, strict=True), start=1):
        print(f"[{stage}/2] {line}", flush=True)
        tic = time.perf_counter()
        subprocess.run(command, check=True)
        print(f"[{stage}/2] done in {time.perf_counter() - tic:.0f} s", flush=True)
    reference = record_reference(root)
    if reference is not None:
        print(f"reference: {reference.name} total reward {reference.total:.2f} (in {root / EXPERIMENT_FILE})")
    print(f"report: {write_report(root, root / REPORT_DIR)}")


if __name__ == "__main__":
    main()
