"""The numbers of Tables 1-6 as pandas DataFrames: per-seed values, then mean ± std over seeds (ddof = 1).

Every statistic is a ``groupby().agg`` of a long-form frame of per-seed values, so the tables,
``tables.json`` and the figures share one definition of mean, standard deviation and seed count.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np
import pandas as pd

from qtl.metrics import area_under_curve, final_performance, time_to_convergence
from qtl.report.approaches import COMPLIANCE_APPROACH
from qtl.report.discover import Cell, Experiment

METRICS: dict[str, Callable[[Sequence[float]], float]] = {
    "final_performance": final_performance,  # Table 1
    "auc": area_under_curve,  # Tables 2 and 5
    "time_to_convergence": time_to_convergence,  # Tables 3 and 6
}
CELL_KEYS = ["approach", "label"]
VALUE = "value"


def _mean(values: pd.Series) -> float:
    """Mean over seeds (numpy's summation, so the numbers match the per-seed arithmetic of earlier reports)."""
    return float(np.mean(values.to_numpy()))


def _sample_std(values: pd.Series) -> float:
    """Standard deviation over seeds with ddof = 1; NaN for a single seed."""
    return float(np.std(values.to_numpy(), ddof=1)) if len(values) > 1 else math.nan


STATS = {"mean": (VALUE, _mean), "std": (VALUE, _sample_std), "n": (VALUE, "size")}


def seed_values(experiment: Experiment) -> pd.DataFrame:
    """Every metric of :data:`METRICS` per seed: columns ``metric, approach, label, seed, value``, table order."""
    rows = [(metric, approach, label, seed, float(summary(cell.curves[seed].returns)))
            for metric, summary in METRICS.items()
            for approach, by_label in experiment.cells.items()
            for label, cell in by_label.items()
            for seed in cell.seeds]
    return pd.DataFrame(rows, columns=["metric", *CELL_KEYS, "seed", VALUE])


def over_seeds(values: pd.DataFrame, keys: Sequence[str]) -> pd.DataFrame:
    """``mean``, ``std`` (ddof = 1; NaN for one seed) and ``n`` of ``value`` per group of ``keys``, in order met."""
    return values.groupby(list(keys), sort=False).agg(**STATS)


def metric_table(experiment: Experiment, metric: str) -> pd.DataFrame:
    """Table 1 (final_performance), 2 (auc) or 3 (time_to_convergence): mean, std, n indexed by (approach, label)."""
    values = seed_values(experiment)
    return over_seeds(values[values["metric"] == metric], CELL_KEYS)


def cell_stats(cell: Cell) -> pd.DataFrame:
    """Every metric of one cell over its seeds (Tables 5 and 6): mean, std, n indexed by metric."""
    values = [(metric, float(summary(cell.curves[seed].returns))) for metric, summary in METRICS.items()
              for seed in cell.seeds]
    return over_seeds(pd.DataFrame(values, columns=["metric", VALUE]), ["metric"])


def compliance_values(experiment: Experiment) -> pd.DataFrame:
    """Task compliance of each run's last (common) episode where it was computed: ``approach, label, seed, value``."""
    rows = [(approach, label, seed, cell.curves[seed].compliance[-1])
            for approach, by_label in experiment.cells.items()
            for label, cell in by_label.items()
            for seed in cell.seeds if not math.isnan(cell.curves[seed].compliance[-1])]
    return pd.DataFrame(rows, columns=[*CELL_KEYS, "seed", VALUE])


def compliance_table(experiment: Experiment) -> pd.DataFrame:
    """Table 4 indexed by label: the approach read (QTL-PILCO Bayesian where it has compliance, else the first
    that has), and mean, std, n of its runs' compliance; labels without any compliance are left out."""
    values = compliance_values(experiment)
    preferred = [COMPLIANCE_APPROACH] + [a for a in experiment.approaches if a != COMPLIANCE_APPROACH]
    chosen = []
    for label in experiment.labels:
        found = values[values["label"] == label]
        approach = next((a for a in preferred if (found["approach"] == a).any()), None)
        if approach is not None:
            chosen.append(found[found["approach"] == approach])
    if not chosen:
        return pd.DataFrame(columns=["approach", *STATS]).rename_axis("label")
    return over_seeds(pd.concat(chosen), CELL_KEYS).reset_index(level="approach")


def per_seed(values: pd.DataFrame) -> dict[str, float]:
    """``{seed: value}`` of a per-seed frame, seeds ascending as strings (the form of ``tables.json``)."""
    ordered = values.sort_values("seed")
    return {str(seed): float(v) for seed, v in zip(ordered["seed"], ordered[VALUE], strict=True)}


def episode_stats(cell: Cell) -> pd.DataFrame:
    """Total reward per episode over the cell's seeds (Figs. 1-3): ``mean`` and ``std`` (ddof = 1) per episode."""
    returns = pd.DataFrame({seed: cell.curves[seed].returns for seed in cell.seeds})  # episodes x seeds
    return pd.DataFrame({"mean": returns.mean(axis=1), "std": returns.std(axis=1)})


def std_or_none(std: float) -> float | None:
    """A standard deviation as ``tables.json`` holds it: None where one seed left it undefined (NaN)."""
    return None if math.isnan(std) else float(std)


JsonStat = dict[str, float | int | dict[str, float] | None]


def stat_json(stats: pd.Series, values: pd.DataFrame) -> JsonStat:
    """Mean, std (None for one seed), number of seeds and the per-seed values of one table cell (``tables.json``):
    ``stats`` a row of :func:`over_seeds`, ``values`` the cell's per-seed frame."""
    return {"mean": float(stats["mean"]), "std": std_or_none(stats["std"]), "n": int(stats["n"]),
            "per_seed": per_seed(values)}


def cells_json(values: pd.DataFrame) -> dict[str, dict[str, JsonStat]]:
    """approach -> label -> :func:`stat_json` of each cell of one metric's per-seed ``values`` (``tables.json``)."""
    by_cell = values.groupby(CELL_KEYS, sort=False)
    table: dict[str, dict[str, JsonStat]] = {}
    for (approach, label), stats in over_seeds(values, CELL_KEYS).iterrows():
        table.setdefault(approach, {})[label] = stat_json(stats, by_cell.get_group((approach, label)))
    return table
