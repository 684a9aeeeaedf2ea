"""The cells of the benchmarks' tables, and the tables themselves (:func:`qtl.report.tables.markdown_table`)."""

from __future__ import annotations

import statistics

from qtl.report.tables import markdown_table

__all__ = ["first_successes", "markdown_table", "mean_std", "model_label"]


def model_label(row: dict) -> str:
    """How a result row's dynamics model reads in a table: 'exact' or 'sparse, m = <inducing inputs>'."""
    return f"sparse, m = {row['inducing']}" if row["model"] == "sparse" else "exact"


def mean_std(values: list[float], digits: int = 1) -> str:
    """Mean ± std over seeds ("—" for none, the value alone for one)."""
    if len(values) < 2:
        return f"{values[0]:.{digits}f}" if values else "—"
    return f"{statistics.mean(values):.{digits}f} ± {statistics.stdev(values):.{digits}f}"


def first_successes(per_seed: list[dict]) -> str:
    """The episode of each seed's first success ("—": none), space-separated."""
    return " ".join("—" if r["first_success"] is None else str(r["first_success"]) for r in per_seed)
