"""Where relapses happen: each learned episode after a run's first success, failed or not, by its start state.

Every run of one seed draws the same start state x_0 ~ N(μ_0, diag(σ_0²)) for an episode (the env's seed is
derived from the run's seed and the episode), whatever the approach or target. So an episode that fails in
most runs of a seed points at its start state, not at the approach. This script reads each run's start
states (from its newest checkpoint's data set) and success tests (``metrics.csv``) and prints

- the failure rate of the learned episodes after the first success, by the start state's percentile in the
  start distribution (P(χ²_D ≤ |z|²), z = (x_0 − μ_0)/σ_0): how far in its tails the policy fails;
- per seed, the episodes that fail in at least half of the runs that had succeeded before them.

It needs every run's newest checkpoint, which a finished sweep kept in git does not hold (docs/experiments/README.md):
without them it stops, in one line, before reading any run.

    python scripts/research/relapse_starts.py runs/experiments/cartpole --finished-only --output relapses.json
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import gymnasium
import numpy as np
import pandas as pd
import torch
import yaml

import qtl.envs  # noqa: F401  (registers the qtl/ environments)
from qtl.checkpoint import CHECKPOINT_DIR, episodes_done, latest_checkpoint, load_checkpoint
from qtl.metrics import first_success
from qtl.report.discover import discover
from qtl.report.paths import recorded_path
from qtl.report.tables import markdown

PERCENTILE_BINS = (0.0, 0.5, 0.75, 0.9, 1.0)  # of the start distribution: the inner half, then the tails
CONFIG = Path(".hydra") / "config.yaml"
SOURCE = "source"


@dataclass(frozen=True)
class Episode:
    """One learned episode after its run's first success."""

    approach: str
    label: str
    seed: int
    episode: int
    radius: float  # |z|, z = (x_0 - μ_0) / σ_0
    percentile: float  # P(χ²_D <= |z|²)
    success: bool


def start_distribution(run_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """μ_0, σ_0 `D` of a run: ``task.start`` of its config where given, else its environment's."""
    config_file = run_dir / CONFIG
    if not config_file.is_file():
        raise SystemExit(f"{run_dir}: no {CONFIG}; run it with qtl-train, which writes the config it ran")
    task = yaml.safe_load(config_file.read_text())["task"]
    kwargs = {k: v for k, v in task["env"].items() if k != "id"}
    env = gymnasium.make(task["env"]["id"], **kwargs).unwrapped
    start = task.get("start") or {}
    mean = start.get("mean") if start.get("mean") is not None else env.start_mean
    std = start.get("std") if start.get("std") is not None else env.start_std
    return np.asarray(mean, dtype=float), np.asarray(std, dtype=float)


def chi2_cdf(square: float, dof: int) -> float:
    """P(χ²_dof <= ``square``): the regularised lower incomplete gamma function."""
    return float(torch.special.gammainc(torch.tensor(dof / 2.0, dtype=torch.float64),
                                        torch.tensor(square / 2.0, dtype=torch.float64)))


def run_episodes(approach: str, label: str, seed: int, run_dir: Path, successes: list[bool]) -> list[Episode]:
    """The episodes after the first success of one run (its first ``len(successes)`` episodes)."""
    first = first_success(successes)
    if first is None:
        return []
    states = load_checkpoint(latest_checkpoint(run_dir))["dataset"]["states"]
    if len(states) < len(successes):
        raise SystemExit(f"{run_dir}: its newest checkpoint holds {len(states)} episodes, metrics.csv "
                         f"{len(successes)}; resume the run (resume=auto) so that the two agree")
    mean, std = start_distribution(run_dir)
    found = []
    for episode in range(first + 1, len(successes)):
        z = (np.asarray(states[episode][0], dtype=float) - mean) / std
        square = float(z @ z)
        found.append(Episode(approach, label, seed, episode, math.sqrt(square), chi2_cdf(square, z.size),
                             successes[episode]))
    return found


def collect(root: Path, finished_only: bool) -> list[Episode]:
    """Every run's episodes after its first success, the sources' (approach and label ``source``) first."""
    experiment = discover(root, finished_only=finished_only)
    runs = [*experiment.source_dirs.values(), *experiment.run_dirs()]
    if missing := [run_dir for run_dir in runs if not episodes_done(run_dir)]:
        raise SystemExit(f"{recorded_path(experiment.root)}: {len(missing)} of {len(runs)} run(s) hold no checkpoint "
                         f"({CHECKPOINT_DIR}/episode_NNNN.pt), whose data set holds the start states, e.g. "
                         f"{missing[0].relative_to(experiment.root)}; a finished sweep kept in git has none: rerun "
                         "its sweep or check out the commit that holds them (docs/experiments/README.md)")
    episodes = []
    for seed, curve in experiment.sources.items():
        episodes += run_episodes(SOURCE, SOURCE, seed, experiment.source_dirs[seed], curve.successes)
    for approach, by_label in experiment.cells.items():
        for label, cell in by_label.items():
            for seed in cell.seeds:
                episodes += run_episodes(approach, label, seed, cell.run_dirs[seed], cell.curves[seed].successes)
    return episodes


def by_percentile(episodes: pd.DataFrame) -> pd.DataFrame:
    """Learned episodes after the first success, their failures and the failure rate, per percentile bin."""
    bins = pd.cut(episodes["percentile"], PERCENTILE_BINS, include_lowest=True)
    groups = episodes.assign(failed=~episodes["success"]).groupby(bins, observed=False)["failed"]
    table = pd.DataFrame({"episodes": groups.size(), "failures": groups.sum()})
    table["failure rate"] = table["failures"] / table["episodes"].where(table["episodes"] > 0)
    return table


def shared_failures(episodes: pd.DataFrame) -> pd.DataFrame:
    """Per (seed, episode): the runs past their first success there and how many failed; those where half or
    more failed, most failures first."""
    frame = episodes.assign(failed=~episodes["success"])
    grouped = frame.groupby(["seed", "episode"]).agg(runs=("failed", "size"), failed=("failed", "sum"),
                                                     radius=("radius", "first"), percentile=("percentile", "first"))
    shared = grouped[grouped["failed"] * 2 >= grouped["runs"]]
    return shared.sort_values(["failed", "percentile"], ascending=False).reset_index()


def _edges() -> list[tuple[float, float]]:
    """The (low, high) percentiles of each bin of :data:`PERCENTILE_BINS`."""
    return list(itertools.pairwise(PERCENTILE_BINS))


def report(episodes: list[Episode]) -> tuple[str, dict[str, object]]:
    """The markdown tables and their numbers as JSON."""
    if not episodes:
        return "No target run has succeeded yet: no episode after a first success to classify.\n", {"episodes": []}
    frame = pd.DataFrame([asdict(e) for e in episodes])
    bins = by_percentile(frame)
    bin_rows = pd.DataFrame({
        "start-state percentile": [f"{low:.0%}–{high:.0%}" for low, high in _edges()],
        "episodes": bins["episodes"].astype(str),
        "failures": bins["failures"].astype(str),
        "failure rate": [("—" if math.isnan(r) else f"{r:.0%}") for r in bins["failure rate"]],
    })
    shared = shared_failures(frame)
    shared_rows = pd.DataFrame({
        "seed": shared["seed"].astype(str), "episode": shared["episode"].astype(str),
        "failed / runs": [f"{f} / {n}" for f, n in zip(shared["failed"], shared["runs"], strict=True)],
        "|z|": [f"{r:.2f}" for r in shared["radius"]],
        "percentile": [f"{p:.0%}" for p in shared["percentile"]],
    })
    total, failed = len(frame), int((~frame["success"]).sum())
    text = (f"{total} learned episodes after their run's first success, {failed} failed ({failed / total:.0%}).\n\n"
            + markdown(bin_rows) + "\n\nEpisodes failed by half or more of the runs of their seed past their "
            "first success (the same start state in every run of a seed):\n\n"
            + (markdown(shared_rows, text_columns=0) if len(shared_rows) else "(none)") + "\n")
    numbers = {
        "episodes": [asdict(e) for e in episodes],
        "by_percentile": [{"low": low, "high": high, "episodes": int(n), "failures": int(f)}
                          for (low, high), n, f in zip(_edges(), bins["episodes"], bins["failures"], strict=True)],
        "shared_failures": shared.to_dict(orient="records"),
    }
    return text, numbers


def main(argv: list[str] | None = None) -> None:
    """Parse the arguments, classify the episodes, print the tables (and write JSON)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("root", type=Path, help="an experiment directory (as qtl-experiment leaves it)")
    parser.add_argument("--finished-only", action="store_true", help="leave out runs short of their episodes")
    parser.add_argument("--output", type=Path, help="also write the numbers as JSON here")
    args = parser.parse_args(argv)
    if not args.root.is_dir():
        parser.error(f"{args.root} is not a directory: give an experiment directory")
    text, numbers = report(collect(args.root, args.finished_only))
    print(text, end="")
    if args.output is not None:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(numbers, indent=2, default=float) + "\n")


if __name__ == "__main__":
    main()
