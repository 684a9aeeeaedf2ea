"""Tables 1-6 and the report's other tables in markdown, through ``DataFrame.to_markdown``."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import pandas as pd

from qtl.metrics import CONVERGED_FRACTION, FINAL_EPISODES
from qtl.report.approaches import approach_name
from qtl.report.discover import Experiment
from qtl.report.stats import cell_stats, compliance_table, metric_table

REWARD_DIGITS = 2  # total rewards and areas, as the paper prints them
EPISODE_DIGITS = 1  # means of episode counts
COMPLIANCE_DIGITS = 2
MISSING = "—"
PLUS_MINUS = " ± "

TITLES: dict[int, str] = {
    1: f"Final performance: total reward averaged over the last {FINAL_EPISODES} episodes.",
    2: "Area under the learning curve (trapezoidal rule over episodes, unit spacing).",
    3: (
        f"Time to convergence: the first episode whose total reward reaches {CONVERGED_FRACTION:.0%} of the "
        "final performance (episode 0 is the initial one)."
    ),
    4: "Task compliance (Eq. 14) of the last episode's model, per target task.",
    5: "Area under the learning curve for the {label} task.",
    6: (
        f"Time to convergence (episodes to reach {CONVERGED_FRACTION:.0%} of the final performance); final "
        f"performance, the total reward averaged over the last {FINAL_EPISODES} episodes, in parentheses."
    ),
}
METRIC_TABLES = ((1, "final_performance"), (2, "auc"), (3, "time_to_convergence"))


def stat_text(mean: float, std: float, digits: int, whole: bool = False) -> str:
    """``mean ± std`` to ``digits`` decimals; the bare value where ``std`` is NaN (one seed), whole if ``whole``."""
    if math.isnan(std):
        return str(round(mean)) if whole else f"{mean:.{digits}f}"
    return f"{mean:.{digits}f}{PLUS_MINUS}{std:.{digits}f}"


ALIGNMENTS = {"l": "left", "r": "right", "c": "center"}


def markdown(frame: pd.DataFrame, text_columns: int = 1, align: str | None = None) -> str:
    """A markdown table of ``frame``'s text cells: ``align`` one letter a column (``l``, ``r`` or ``c``), by default
    its first ``text_columns`` columns left-aligned and the others right. Every table of qtl is written here."""
    letters = align if align is not None else "l" * text_columns + "r" * (frame.shape[1] - text_columns)
    if len(letters) != frame.shape[1] or set(letters) - set(ALIGNMENTS):
        raise ValueError(f"align {letters!r}: give one of {'/'.join(ALIGNMENTS)} for each of {frame.shape[1]} columns")
    return frame.to_markdown(index=False, colalign=[ALIGNMENTS[a] for a in letters], disable_numparse=True)


def markdown_table(rows: Iterable[Sequence[object]], columns: Sequence[str], align: str | None = None) -> str:
    """A markdown table of ``rows`` under ``columns``, each cell as ``str`` writes it; ``align`` as :func:`markdown`'s
    (by default the first column left, the others right)."""
    frame = pd.DataFrame([[str(cell) for cell in row] for row in rows], columns=list(columns))
    return markdown(frame, align=align)


def seed_counts(counts: Sequence[int]) -> str:
    """The seeds column: one number when every cell of the row has as many seeds, else one per cell."""
    return str(counts[0]) if len(set(counts)) == 1 else ", ".join(map(str, counts))


def table_heading(number: int, **fields: str) -> str:
    """``**Table n.** title`` as the paper captions its tables."""
    return f"**Table {number}.** {TITLES[number].format(**fields)}"


def metric_markdown(experiment: Experiment, number: int, metric: str) -> str:
    """Table 1, 2 or 3: rows approaches, columns labels, ``mean ± std`` cells, seeds per row."""
    stats = metric_table(experiment, metric)
    whole = metric == "time_to_convergence"
    digits = EPISODE_DIGITS if whole else REWARD_DIGITS
    text = pd.Series([stat_text(m, s, digits, whole) for m, s in zip(stats["mean"], stats["std"], strict=True)],
                     index=stats.index)
    return table_heading(number) + "\n\n" + approach_grid(text, stats["n"], experiment.approaches, experiment.labels)


def approach_grid(text: pd.Series, seeds: pd.Series, approaches: Sequence[str], labels: Sequence[str]) -> str:
    """A markdown table of cell ``text`` indexed by (approach, label): rows approaches by the paper's names,
    columns labels (a dash where a cell is missing), and the seeds per row from ``seeds`` (same index)."""
    grid = text.unstack("label").reindex(index=list(approaches), columns=list(labels)).fillna(MISSING)
    counts = seeds.groupby(level="approach", sort=False).agg(lambda n: seed_counts(list(n)))
    grid.insert(0, "Approach", [approach_name(a) for a in grid.index])
    grid["Seeds"] = counts.reindex(grid.index).fillna(MISSING)  # an approach with no cell in this table
    return markdown(grid)


def compliance_markdown(experiment: Experiment) -> str | None:
    """Table 4: one row per label with task compliance; None when no run computed compliance."""
    table = compliance_table(experiment)
    if table.empty:
        return None
    rows = pd.DataFrame({
        "Target": table.index,
        "Approach": [approach_name(a) for a in table["approach"]],
        "Task compliance": [stat_text(m, s, COMPLIANCE_DIGITS) for m, s in zip(table["mean"], table["std"],
                                                                               strict=True)],
        "Seeds": [str(int(n)) for n in table["n"]],
    })
    return table_heading(4) + "\n\n" + markdown(rows, text_columns=2)


def single_label_markdown(experiment: Experiment) -> tuple[str, str]:
    """Tables 5 (area under the curve) and 6 (time to convergence (final performance)) of a one-label experiment."""
    (label,) = experiment.labels
    auc_rows, convergence_rows = [], []
    for approach in experiment.approaches:
        cell = experiment.cell(approach, label)
        assert cell is not None  # one label: every approach present has it
        stats = cell_stats(cell)
        auc, ttc, final = (stats.loc[m] for m in ("auc", "time_to_convergence", "final_performance"))
        auc_text = stat_text(auc["mean"], auc["std"], REWARD_DIGITS)
        auc_rows.append([approach_name(approach), auc_text, str(int(auc["n"]))])
        convergence = (f"{stat_text(ttc['mean'], ttc['std'], EPISODE_DIGITS, whole=True)} "
                       f"({stat_text(final['mean'], final['std'], REWARD_DIGITS)})")
        convergence_rows.append([approach_name(approach), convergence, str(int(ttc["n"]))])
    table5 = pd.DataFrame(auc_rows, columns=["Approach", "Area under curve", "Seeds"])
    table6 = pd.DataFrame(convergence_rows, columns=["Approach", "Time to convergence (final performance)", "Seeds"])
    return (table_heading(5, label=label) + "\n\n" + markdown(table5),
            table_heading(6) + "\n\n" + markdown(table6))


def tables_markdown(experiment: Experiment) -> list[str]:
    """Every table of the report: Tables 1-3, Table 4 if any compliance, Tables 5-6 for one label."""
    tables = [metric_markdown(experiment, number, metric) for number, metric in METRIC_TABLES]
    compliance = compliance_markdown(experiment)
    if compliance is not None:
        tables.append(compliance)
    if len(experiment.labels) == 1:
        tables += single_label_markdown(experiment)
    return tables


def table_numbers(experiment: Experiment) -> list[int]:
    """The numbers of the tables the report holds: 1-3, 4 with compliance, 5-6 for one label."""
    numbers = [number for number, _ in METRIC_TABLES]
    numbers += [4] if not compliance_table(experiment).empty else []
    return numbers + ([5, 6] if len(experiment.labels) == 1 else [])
