"""The benchmarks' shared plumbing (``scripts/bench_*.py``): what they record, their tables and their runs.

:mod:`~qtl.bench.record` names the machine, date, commit and command and writes the JSON and the section of
``docs/benchmarks.md``; :mod:`~qtl.bench.cells` formats the tables' cells and the tables
(:func:`qtl.report.tables.markdown_table`, as the report's); :mod:`~qtl.bench.runs` parses options with Hydra
overrides after them and makes learning runs in parallel. The cases several benchmarks share have modules of their
own: :mod:`~qtl.bench.search` (cart-pole data, the loop's search settings), :mod:`~qtl.bench.scale` (the full-scale
presets' stages), :mod:`~qtl.bench.synthetic` (the rollout benchmarks' synthetic GP), :mod:`~qtl.bench.refit` (a
finished run's model, refitted as its next episode would fit it) and :mod:`~qtl.bench.constraints` (a run's crossings
of declared state bounds and its cost per search evaluation). Benchmarks write into the clone the package is
installed from (editable, :data:`~qtl.bench.record.ROOT`).
"""

from __future__ import annotations

from qtl.bench.cells import first_successes, markdown_table, mean_std, model_label
from qtl.bench.record import (
    BENCHMARKS_MD,
    ROOT,
    command_line,
    commit,
    display_path,
    machine,
    peak_rss_mib,
    relative_token,
    today,
    write_results,
    write_section,
)
from qtl.bench.runs import (
    add_learning_arguments,
    initial_episodes,
    parse_with_overrides,
    read_csv,
    run_all,
    run_seed,
)

__all__ = [
    "BENCHMARKS_MD",
    "ROOT",
    "add_learning_arguments",
    "command_line",
    "commit",
    "display_path",
    "first_successes",
    "initial_episodes",
    "machine",
    "markdown_table",
    "mean_std",
    "model_label",
    "parse_with_overrides",
    "peak_rss_mib",
    "read_csv",
    "relative_token",
    "run_all",
    "run_seed",
    "today",
    "write_results",
    "write_section",
]
