"""Final policies from the same K start states (not in the paper): ``final_policies.json`` beside the runs.

Table 1 averages a run's last 3 episodes, 3 start states per seed; ``qtl-evaluate`` (:mod:`qtl.pipeline.evaluate`)
runs each run's last policy from K start states shared by every run and writes what it found to
``<root>/final_policies.json``. The report reads it back here, keeping only evaluations of each run's last
episode: a run that has gone on since it was evaluated is named, not counted.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from qtl.report.discover import SEED_PREFIX, Experiment
from qtl.report.paths import recorded_path
from qtl.report.stats import CELL_KEYS, VALUE, cells_json, over_seeds, stat_json
from qtl.report.tables import REWARD_DIGITS, approach_grid, stat_text

FINAL_POLICIES_FILE = "final_policies.json"
SOURCE = "source"  # the approach and label of a source run in ``final_policies.json``
EVALUATE_COMMAND = "qtl-evaluate {root} --finished-only"
FINAL_METRICS: dict[str, str] = {
    "success_rate": "**Table F1.** Final policies: the share of the {starts} start states from which the run's last "
                    "policy passes the success test, in %; mean ± std over seeds.",
    "mean_return": "**Table F2.** Final policies: total reward averaged over the {starts} start states; mean ± std "
                   "over seeds.",
}
PERCENT = {"success_rate": True, "mean_return": False}


@dataclass(frozen=True)
class FinalPolicies:
    """The evaluations of ``final_policies.json`` that belong to the report's runs."""

    starts: int
    eval_seed: int
    values: pd.DataFrame  # metric, approach, label, seed, value: target runs evaluated at their last episode
    sources: pd.DataFrame  # metric, seed, value: the same for the source runs
    stale: list[str]  # the report's runs without an evaluation of their last episode, "<approach>/<label>/seed_<s>"


def read_final_policies(experiment: Experiment, path: Path | None = None) -> FinalPolicies | None:
    """The evaluations in ``path`` (default ``<root>/final_policies.json``) of the runs in ``experiment``; None
    without the file."""
    path = experiment.root / FINAL_POLICIES_FILE if path is None else path
    if not path.is_file():
        return None
    try:
        numbers = json.loads(path.read_text())
        starts, eval_seed = int(numbers["starts"]), int(numbers["eval_seed"])
        # run -> (the episode whose policy was evaluated, {metric: value}), every field read and cast here
        by_run = {(r["approach"], r["label"], int(r["seed"])):
                  (int(r["episode"]), {metric: float(r[metric]) for metric in FINAL_METRICS}) for r in numbers["runs"]}
    except (ValueError, KeyError, TypeError) as err:
        command = EVALUATE_COMMAND.format(root=recorded_path(experiment.root))
        raise ValueError(f"{path} is not what qtl-evaluate writes ({type(err).__name__}: {err}); "
                         f"move it away or rerun `{command}`") from err
    rows, source_rows, stale = [], [], []

    def evaluation(approach: str, label: str, seed: int, episodes: int) -> dict[str, float] | None:
        episode, values = by_run.get((approach, label, seed), (None, {}))
        if episode != episodes - 1:
            stale.append(f"{approach}/{label}/{SEED_PREFIX}{seed}")
            return None
        return values

    for seed, curve in experiment.sources.items():
        if (found := evaluation(SOURCE, SOURCE, seed, len(curve.returns))) is not None:
            source_rows += [(metric, seed, found[metric]) for metric in FINAL_METRICS]
    for approach, by_label in experiment.cells.items():
        for label, cell in by_label.items():
            for seed in cell.seeds:
                if (found := evaluation(approach, label, seed, cell.lengths[seed])) is not None:
                    rows += [(metric, approach, label, seed, found[metric]) for metric in FINAL_METRICS]
    return FinalPolicies(starts, eval_seed,
                         pd.DataFrame(rows, columns=["metric", *CELL_KEYS, "seed", VALUE]),
                         pd.DataFrame(source_rows, columns=["metric", "seed", VALUE]), stale)


def _text(metric: str, mean: float, std: float) -> str:
    """One cell: a percentage without decimals, a total reward with the paper's two."""
    if PERCENT[metric]:
        return stat_text(100.0 * mean, 100.0 * std, 0)
    return stat_text(mean, std, REWARD_DIGITS)


def final_tables(found: FinalPolicies, approaches: list[str], labels: list[str]) -> list[str]:
    """Tables F1-F2: rows approaches, columns labels, ``mean ± std`` over the seeds evaluated, seeds per row."""
    tables = []
    for metric, title in FINAL_METRICS.items():
        stats = over_seeds(found.values[found.values["metric"] == metric], CELL_KEYS)
        text = pd.Series([_text(metric, m, s) for m, s in zip(stats["mean"], stats["std"], strict=True)],
                         index=stats.index, dtype=object)
        table = approach_grid(text, stats["n"], approaches, labels) if len(stats) else "No run evaluated."
        tables.append(title.format(starts=found.starts) + "\n\n" + table)
    return tables


def final_policies_markdown(found: FinalPolicies, experiment: Experiment, root_text: str | Path) -> str:
    """The report's section body: how the start states were drawn, Tables F1-F2, the sources and the runs left
    out."""
    parts = [f"Each run's last policy, run on its own task from the same {found.starts} start states (drawn with "
             f"seed {found.eval_seed}, none of them a training episode's start), by `"
             f"{EVALUATE_COMMAND.format(root=root_text)}` (it writes `{FINAL_POLICIES_FILE}`).",
             *final_tables(found, experiment.approaches, experiment.labels)]
    if not found.sources.empty:
        sources = over_seeds(found.sources, ["metric"])
        cells = [_text(metric, sources.loc[metric, "mean"], sources.loc[metric, "std"]) + (" %" if PERCENT[metric]
                 else "") for metric in FINAL_METRICS]
        parts.append(f"Sources ({int(sources['n'].iloc[0])} seeds): success {cells[0]}, total reward {cells[1]}.")
    if found.stale:
        parts.append(f"Not in these tables, their last policy not evaluated ({len(found.stale)} run(s); rerun the "
                     "command above): " + ", ".join(found.stale) + ".")
    return "\n\n".join(parts)


def final_policies_json(found: FinalPolicies) -> dict[str, object]:
    """Tables F1-F2 for ``tables.json``: metric -> approach -> label -> mean, std, n and per-seed values, with the
    start states' count and seed and the runs left out."""
    out: dict[str, object] = {"starts": found.starts, "eval_seed": found.eval_seed, "stale": found.stale}
    for metric in FINAL_METRICS:
        out[metric] = cells_json(found.values[found.values["metric"] == metric])
        sources = found.sources[found.sources["metric"] == metric]
        out[f"source_{metric}"] = (None if sources.empty else
                                   stat_json(over_seeds(sources, ["metric"]).loc[metric], sources))
    return out

