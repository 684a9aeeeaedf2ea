"""The paper's published numbers (Section 5, Tables 1-6), and the report's tables set beside them.

The values are transcribed from the paper's tables as printed: ``NC`` is its "no convergence" and
``unknown`` its "Unknown" (Table 3, where a run did not converge). A cell of a "beside the paper" table
reads ``here · paper``: this experiment's mean ± std over seeds, then the paper's value (to the report's
decimals).
"""

from __future__ import annotations

from collections.abc import Sequence

import pandas as pd

from qtl.report.discover import Experiment
from qtl.report.stats import CELL_KEYS, VALUE, compliance_table, metric_table
from qtl.report.successes import success_values
from qtl.report.tables import (
    COMPLIANCE_DIGITS,
    EPISODE_DIGITS,
    METRIC_TABLES,
    MISSING,
    REWARD_DIGITS,
    TITLES,
    approach_grid,
    markdown,
    stat_text,
)

NC = "NC"  # the paper's "no convergence" (Table 1)
UNKNOWN = "unknown"  # the paper's "Unknown" time to convergence (Table 3)
BESIDE = " · "  # between this experiment's cell and the paper's

PaperValue = float | str
PaperTable = dict[str, dict[str, PaperValue]]  # approach -> label -> value

_APPROACH_ROWS = ("pilco", "hyperparameters_transfer", "qtl_gamma_09", "qtl_gamma_05", "qtl_gamma_1",
                  "qtl_bayesian", "policy_transfer")  # the row order of Tables 1-3
_CARTPOLE_LABELS = ("m0.8", "m1.0", "m1.5", "m2.0")  # the columns of Tables 1-3: the pole's mass in kg


def _cartpole(rows: Sequence[tuple[PaperValue, ...]]) -> PaperTable:
    """One of Tables 1-3: its rows (in the paper's order) keyed by approach preset and pole-mass label."""
    return {approach: dict(zip(_CARTPOLE_LABELS, row, strict=True))
            for approach, row in zip(_APPROACH_ROWS, rows, strict=True)}


# experiment name -> metric -> approach -> label -> value; the table each metric comes from in PAPER_SOURCE.
PAPER: dict[str, dict[str, PaperTable]] = {
    "cartpole": {
        "final_performance": _cartpole([  # Table 1
            (36.95, 35.53, 33.32, 29.71),
            (37.08, 33.04, 32.98, 29.66),
            (37.55, 34.97, 32.84, 29.79),
            (37.20, 34.50, 32.78, 29.90),
            (37.06, 34.59, NC, NC),
            (37.57, 35.66, 32.68, 29.97),
            (35.77, 32.81, NC, NC),
        ]),
        "auc": _cartpole([  # Table 2
            (228.47, 206.09, 218.63, 204.41),
            (236.59, 185.99, 260.33, 240.98),
            (287.44, 236.20, 589.57, 527.65),
            (240.86, 217.40, 415.95, 366.68),
            (246.41, 212.92, 146.44, 117.63),
            (272.91, 236.43, 602.55, 539.79),
            (214.35, 156.76, 173.90, 150.64),
        ]),
        "time_to_convergence": _cartpole([  # Table 3
            (9, 10, 22, 25),
            (9, 11, 22, 25),
            (7, 9, 9, 12),
            (9, 10, 20, 21),
            (9, 10, UNKNOWN, UNKNOWN),
            (8, 9, 10, 12),
            (10, 11, UNKNOWN, UNKNOWN),
        ]),
    },
    "aircraft": {
        "final_performance": {"pilco": {"helicopter": 132.5}, "qtl_bayesian": {"helicopter": 131.99}},  # Table 6
        "auc": {"pilco": {"helicopter": 2225.4}, "qtl_bayesian": {"helicopter": 3803.7}},  # Table 5
        "time_to_convergence": {"pilco": {"helicopter": 24}, "qtl_bayesian": {"helicopter": 19}},  # Table 6
    },
}
PAPER_SOURCE: dict[str, dict[str, int]] = {  # experiment -> metric -> the paper's table number
    "cartpole": {"final_performance": 1, "auc": 2, "time_to_convergence": 3},
    "aircraft": {"final_performance": 6, "auc": 5, "time_to_convergence": 6},
}
# experiment name -> label -> task compliance (Table 4: mountain car, engine power relative to the source's).
PAPER_COMPLIANCE: dict[str, dict[str, float]] = {"mountaincar": {"p0.5": 0.64, "p1.5": 0.76, "p3.0": 0.34}}

_OWN_TABLE = {metric: number for number, metric in METRIC_TABLES}  # metric -> this report's table (its title)
_DIGITS = {"final_performance": REWARD_DIGITS, "auc": REWARD_DIGITS, "time_to_convergence": EPISODE_DIGITS}
_NOTES = {
    "auc": ("The paper does not say over which episodes, at what spacing or with which reward its areas are "
            "taken, so only their order within a column compares."),
}


def paper_text(value: PaperValue | None, digits: int, whole: bool = False) -> str:
    """A paper value as printed: a number to ``digits`` decimals (whole if ``whole``), NC or unknown as they are."""
    if value is None:
        return MISSING
    if isinstance(value, str):
        return value
    return str(round(value)) if whole else f"{value:.{digits}f}"


def paper_json(experiment: Experiment) -> dict[str, object] | None:
    """The paper's numbers for this experiment's tables (by metric, approach and label), or None when it has none."""
    name = experiment.name or ""
    if name not in PAPER and name not in PAPER_COMPLIANCE:
        return None
    return {"tables": PAPER_SOURCE.get(name, {}), **PAPER.get(name, {}),
            "compliance": PAPER_COMPLIANCE.get(name, {})}


def _unconverged(experiment: Experiment) -> pd.Series:
    """Per (approach, label): `` (NC k/n)`` where k of n seeds fail every one of Table 1's episodes, else ``""``."""
    values = success_values(experiment)
    finals = values[values["metric"] == "final_successes"].groupby(CELL_KEYS, sort=False)[VALUE]
    return finals.agg(lambda v: f" ({NC} {int((v == 0).sum())}/{len(v)})" if (v == 0).any() else "")


def _metric_beside(experiment: Experiment, metric: str, paper: PaperTable) -> str:
    """One metric's grid: rows approaches, columns labels, cells ``here · paper`` (Table 1's with its NC seeds)."""
    stats = metric_table(experiment, metric)
    whole = metric == "time_to_convergence"
    digits = _DIGITS[metric]
    nc = _unconverged(experiment) if metric == "final_performance" else pd.Series(dtype=str)
    text = pd.Series(
        [stat_text(m, s, digits, whole) + nc.get((a, label), "") + BESIDE
         + paper_text(paper.get(a, {}).get(label), digits, whole)
         for (a, label), m, s in zip(stats.index, stats["mean"], stats["std"], strict=True)],
        index=stats.index)
    return approach_grid(text, stats["n"], experiment.approaches, experiment.labels)


def _compliance_beside(experiment: Experiment, paper: dict[str, float]) -> str | None:
    """Table 4's rows with the paper's compliance beside them; None when no run computed compliance."""
    table = compliance_table(experiment)
    if table.empty:
        return None
    rows = pd.DataFrame({
        "Target": table.index,
        "Task compliance, here": [stat_text(m, s, COMPLIANCE_DIGITS) for m, s in zip(table["mean"], table["std"],
                                                                                     strict=True)],
        "paper (Table 4)": [paper_text(paper.get(label), COMPLIANCE_DIGITS) for label in table.index],
        "Seeds": [str(int(n)) for n in table["n"]],
    })
    return "**Table 4 beside the paper.** " + TITLES[4] + "\n\n" + markdown(rows, text_columns=1)


def beside_paper_markdown(experiment: Experiment) -> str | None:
    """The report's tables with the paper's values beside each cell (``here · paper``); None for other experiments."""
    name = experiment.name or ""
    tables = []
    for metric, paper in PAPER.get(name, {}).items():
        number = PAPER_SOURCE[name][metric]
        title = TITLES[_OWN_TABLE[metric]]
        heading = f"**Table {number} beside the paper.** {title}"
        note = _NOTES.get(metric)
        tables.append(heading + (f" {note}" if note else "") + "\n\n" + _metric_beside(experiment, metric, paper))
    if tables:
        tables.insert(0, f"Each cell: this experiment's mean ± std over seeds{BESIDE}the paper's value ({NC}: no "
                         f"convergence; {UNKNOWN}: the paper's \"Unknown\"; {MISSING}: not in this experiment or not "
                         f"in the paper). In the final performance, ({NC} k/n) after a mean: k of its n seeds pass no "
                         "success test in the episodes it averages (Table S3's 0).")
    if name in PAPER_COMPLIANCE:
        compliance = _compliance_beside(experiment, PAPER_COMPLIANCE[name])
        if compliance is not None:
            tables.append(compliance)
    return "\n\n".join(tables) if tables else None
