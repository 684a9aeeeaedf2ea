"""qtl-evaluate: the final policy of every finished run, tried from the same K start states on the real system.

Table 1's final performance is the mean return of a run's last 3 episodes: 3 start states per seed, shared by
every run of that seed, so one hard start in them moves a whole column (see ``scripts/research/relapse_starts.py``).
This command loads each run's newest checkpoint (the policy that ran its last episode), runs it on the run's
own task from K start states x_0 ~ N(μ_0, Σ_0) drawn once for all runs (``--eval-seed``; none of them is a
training episode's), prints per approach and target the success rate and mean return over those starts
(Tables F1-F2, mean ± std over seeds) and writes every run's numbers to ``<root>/final_policies.json``, where
``qtl-report`` reads them back. No model is fitted and nothing in the run directories is written.
It needs every run's checkpoints, which a finished sweep in git does not keep (docs/experiments/README.md): a run
without them is refused, with the others, before anything is run.

    qtl-evaluate runs/experiments/cartpole --finished-only --starts 100
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

import qtl.envs  # noqa: F401  (registers the qtl/ environments)
from qtl.checkpoint import CHECKPOINT_DIR, episodes_done
from qtl.episodes import run_episode
from qtl.report.discover import Experiment, discover
from qtl.report.final_policies import (
    FINAL_POLICIES_FILE,
    SOURCE,
    final_policies_markdown,
    read_final_policies,
)
from qtl.report.paths import recorded_path
from qtl.runs import load_run
from qtl.seeding import ENV_STREAM, derive_seed

PROG = "qtl-evaluate"
EVAL_SEED = 1_000_003  # the start states' seed: not a run seed of any sweep, so no start is a training episode's
NAMED = 3  # runs named in a refusal; the others counted


@dataclass(frozen=True)
class Evaluation:
    """One run's final policy over the K start states."""

    approach: str
    label: str
    seed: int
    episode: int  # the checkpoint's episode: the last one the policy ran
    success_rate: float
    mean_return: float
    returns: list[float]


def evaluate_run(approach: str, label: str, seed: int, run_dir: Path, episodes: int, starts: int,
                 eval_seed: int) -> Evaluation:
    """Run the policy of ``run_dir``'s newest checkpoint from ``starts`` start states on its own task.

    The run is rebuilt from its stored config as migrated (:func:`qtl.runs.load_run`): a key the run predates
    takes the value the run ran with, not today's default.
    """
    run = load_run(run_dir, overrides=["device=cpu"])
    if run.episode + 1 != episodes:
        raise SystemExit(f"{run_dir}: its newest checkpoint is of episode {run.episode}, its metrics.csv "
                         f"has {episodes} episodes; resume the run (resume=auto) so that the two agree")
    parts = run.parts
    actor = parts.actor(run.policy())
    returns, successes = [], []
    with parts.task.make_env() as env, torch.no_grad():
        for k in range(starts):
            episode = run_episode(env, parts.task, actor, derive_seed(eval_seed, k, ENV_STREAM))
            returns.append(float(episode.rewards.sum()))
            successes.append(parts.task.succeeded(episode.states))
    return Evaluation(approach, label, seed, run.episode, float(np.mean(successes)),
                      float(np.mean(returns)), returns)


def runs_of(experiment: Experiment) -> list[tuple[str, str, int, Path, int]]:
    """(approach, label, seed, run dir, episodes) of every run: the sources' (approach and label ``source``) first."""
    runs = [(SOURCE, SOURCE, seed, experiment.source_dirs[seed], len(curve.returns))
            for seed, curve in experiment.sources.items()]
    return runs + [(approach, label, seed, cell.run_dirs[seed], cell.lengths[seed])
                   for approach, by_label in experiment.cells.items() for label, cell in by_label.items()
                   for seed in cell.seeds]


def unevaluable(experiment: Experiment) -> str | None:
    """What keeps the runs' final policies from being run, in one line (checked before any is), or None.

    Each run needs a checkpoint of its last episode, ``<run>/checkpoints/episode_NNNN.pt``.
    """
    missing, behind = [], []
    for _, _, _, run_dir, episodes in runs_of(experiment):
        made = episodes_done(run_dir)
        name = str(run_dir.relative_to(experiment.root))
        if made == 0:
            missing.append(name)
        elif made != episodes:
            behind.append(f"{name} ({made} checkpointed, {episodes} in metrics.csv)")
    if missing:
        return (f"{recorded_path(experiment.root)}: {len(missing)} of {len(runs_of(experiment))} run(s) hold no "
                f"checkpoint ({CHECKPOINT_DIR}/episode_NNNN.pt), whose policy this command runs: {_named(missing)}; "
                "a finished sweep kept in git has none: rerun its sweep (the same command makes the same runs) or "
                "check out the commit that holds them (docs/experiments/README.md)")
    if behind:
        return (f"{recorded_path(experiment.root)}: the newest checkpoint is not of the last episode in "
                f"{len(behind)} run(s): {_named(behind)}; resume them (resume=auto) so that the two agree")
    return None


def _named(runs: list[str]) -> str:
    """The first :data:`NAMED` of ``runs``, the others counted."""
    more = f" and {len(runs) - NAMED} more" if len(runs) > NAMED else ""
    return ", ".join(runs[:NAMED]) + more


def evaluate(experiment: Experiment, starts: int, eval_seed: int) -> list[Evaluation]:
    """Every run's final policy: the sources' (approach and label ``source``) first, then the targets'."""
    found = []
    for approach, label, seed, run_dir, episodes in runs_of(experiment):
        tic = time.perf_counter()
        found.append(evaluate_run(approach, label, seed, run_dir, episodes, starts, eval_seed))
        print(f"{run_dir.relative_to(experiment.root)}: success {found[-1].success_rate:.0%}, mean return "
              f"{found[-1].mean_return:.2f} ({time.perf_counter() - tic:.1f} s)", file=sys.stderr)
    return found


def main(argv: Sequence[str] | None = None) -> None:
    """Parse the arguments, evaluate the final policies, print the tables (and write JSON)."""
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("root", type=Path, help="an experiment directory (as qtl-experiment leaves it)")
    parser.add_argument("--finished-only", action="store_true", help="leave out runs short of their episodes")
    parser.add_argument("--starts", type=int, default=100, help="start states per policy (default 100)")
    parser.add_argument("--eval-seed", type=int, default=EVAL_SEED, help="seed of the start states")
    parser.add_argument("--output", type=Path,
                        help=f"where every run's numbers go as JSON (default: <root>/{FINAL_POLICIES_FILE}, "
                             "which qtl-report reads)")
    args = parser.parse_args(argv)
    if not args.root.is_dir():
        parser.error(f"{args.root} is not a directory: give an experiment directory")
    if args.starts < 1:
        parser.error(f"--starts {args.starts}: give at least one start state")
    torch.set_num_threads(1)
    try:
        experiment = discover(args.root, finished_only=args.finished_only)
    except ValueError as err:  # no target run (finished, with --finished-only) under root
        parser.error(str(err))
    if (problem := unevaluable(experiment)) is not None:
        parser.error(problem)
    evaluations = evaluate(experiment, args.starts, args.eval_seed)
    output = args.output or experiment.root / FINAL_POLICIES_FILE
    output.parent.mkdir(parents=True, exist_ok=True)
    numbers = {"starts": args.starts, "eval_seed": args.eval_seed, "runs": [asdict(e) for e in evaluations]}
    output.write_text(json.dumps(numbers, indent=2, allow_nan=False) + "\n")
    found = read_final_policies(experiment, output)  # read back: what the report will read
    assert found is not None, output
    print(f"Written to {output}.\n\n" + final_policies_markdown(found, experiment, recorded_path(experiment.root)))


if __name__ == "__main__":
    main()
