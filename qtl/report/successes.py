"""Tables S1-S3 (not in the paper): first success, relapses after it and successes at the end, per approach.

The paper's Tables 1-3 summarise total rewards; whether a run has solved the task, lost it again or ends
unsolved (its "NC", no convergence) is read from each episode's success test (``metrics.csv``'s ``success``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import pandas as pd

from qtl.metrics import FINAL_EPISODES, final_successes, first_success, relapses
from qtl.report.discover import SEED_PREFIX, Experiment
from qtl.report.stats import CELL_KEYS, VALUE, per_seed, std_or_none
from qtl.report.tables import EPISODE_DIGITS, MISSING, approach_grid, stat_text

SUCCESS_METRICS: dict[str, Callable[[Sequence[bool]], int | None]] = {
    "first_success": first_success,  # Table S1
    "relapses": relapses,  # Table S2
    "final_successes": final_successes,  # Table S3
}
SUCCESS_TITLES: dict[str, str] = {
    "first_success": (
        "**Table S1.** First success: the first episode that passes the task's success test (episode 0 is the "
        "initial one); mean ± std over the seeds that pass it, and how many of the seeds do in parentheses."
    ),
    "relapses": (
        "**Table S2.** Relapses: episodes after the first success that fail the success test; mean ± std over "
        "the seeds that succeed."
    ),
    "final_successes": (
        f"**Table S3.** Successes among the last {FINAL_EPISODES} episodes (Table 1's episodes; 0 for every seed "
        "is the paper's NC, no convergence); mean ± std over seeds."
    ),
}


def success_values(experiment: Experiment) -> pd.DataFrame:
    """Every measure of :data:`SUCCESS_METRICS` per seed: ``metric, approach, label, seed, value`` (NaN: none)."""
    rows = []
    for metric, measure in SUCCESS_METRICS.items():
        for approach, by_label in experiment.cells.items():
            for label, cell in by_label.items():
                for seed in cell.seeds:
                    value = measure(cell.curves[seed].successes)
                    rows.append((metric, approach, label, seed, math.nan if value is None else float(value)))
    return pd.DataFrame(rows, columns=["metric", *CELL_KEYS, "seed", VALUE])


def success_table(values: pd.DataFrame) -> pd.DataFrame:
    """``mean``, ``std`` (ddof = 1; NaN for one value) and ``n`` over the seeds with a value, and ``seeds`` in all,
    per (approach, label) of one measure's per-seed ``values``."""
    groups = values.groupby(CELL_KEYS, sort=False)[VALUE]
    return pd.DataFrame({
        "mean": groups.mean(),
        "std": groups.std(ddof=1),  # NaN for fewer than two values, as stat_text expects
        "n": groups.count(),
        "seeds": groups.size(),
    })


def _cell_text(metric: str, row: pd.Series) -> str:
    """One cell: ``mean ± std`` (one decimal), ``(k/n)`` seeds after the first success's; a dash for no value."""
    text = MISSING if row["n"] == 0 else stat_text(row["mean"], row["std"], EPISODE_DIGITS)
    return f"{text} ({int(row['n'])}/{int(row['seeds'])})" if metric == "first_success" else text


def unconverged_runs(experiment: Experiment) -> list[tuple[str, int | None]]:
    """The runs with no success among Table 1's last episodes (the paper's NC), as ``<approach>/<label>/seed_<s>``,
    each with its first success (None: it never succeeded)."""
    return [(f"{approach}/{label}/{SEED_PREFIX}{seed}", first_success(cell.curves[seed].successes))
            for approach, by_label in experiment.cells.items() for label, cell in by_label.items()
            for seed in cell.seeds if final_successes(cell.curves[seed].successes) == 0]


def success_markdown(experiment: Experiment) -> list[str]:
    """Tables S1-S3 (rows approaches, columns labels, seeds per row) and the runs that did not converge."""
    values = success_values(experiment)
    tables = []
    for metric in SUCCESS_METRICS:
        stats = success_table(values[values["metric"] == metric])
        text = pd.Series([_cell_text(metric, row) for _, row in stats.iterrows()], index=stats.index)
        grid = approach_grid(text, stats["seeds"], experiment.approaches, experiment.labels)
        tables.append(SUCCESS_TITLES[metric] + "\n\n" + grid)
    unconverged = unconverged_runs(experiment)
    runs = ", ".join(f"{run} ({'never succeeded' if first is None else f'first success at episode {first}'})"
                     for run, first in unconverged)
    tables.append(f"Runs with no success among the last {FINAL_EPISODES} episodes (NC): "
                  + (f"{len(unconverged)}: {runs}." if unconverged else "none."))
    return tables


def success_json(experiment: Experiment) -> dict[str, dict[str, object]]:
    """Tables S1-S3 for ``tables.json``: metric -> approach -> label -> mean, std, n, seeds and per-seed values
    (null where a seed has none: no success); and ``unconverged``: each NC run -> its first success (null: none)."""
    values = success_values(experiment)
    out: dict[str, dict[str, object]] = {}
    for metric in SUCCESS_METRICS:
        of_metric = values[values["metric"] == metric]
        by_cell = of_metric.groupby(CELL_KEYS, sort=False)
        table = out[metric] = {}
        for (approach, label), row in success_table(of_metric).iterrows():
            values_of_cell = per_seed(by_cell.get_group((approach, label)))
            seeds = {s: (None if math.isnan(v) else v) for s, v in values_of_cell.items()}
            table.setdefault(approach, {})[label] = {
                "mean": None if row["n"] == 0 else float(row["mean"]), "std": std_or_none(row["std"]),
                "n": int(row["n"]), "seeds": int(row["seeds"]), "per_seed": seeds,
            }
    out["unconverged"] = {run: first for run, first in unconverged_runs(experiment)}
    return out
