"""The report of an experiment directory: ``report.md``, ``tables.json`` and the learning-curve figure.

Every number is a mean over seeds ± its standard deviation (ddof = 1), over each cell's common episodes.

    >>> write_report("runs/cartpole")  # doctest: +SKIP
    PosixPath('runs/cartpole/report/report.md')
"""

from __future__ import annotations

import json
import logging
import shlex
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from qtl.report.approaches import approach_name
from qtl.report.autopilot import flies_helicopter
from qtl.report.discover import OVERRIDES_FILE, SEED_PREFIX, Experiment, discover, run_overrides
from qtl.report.figures import FIGURE_STEM, plot_learning_curves
from qtl.report.final_policies import (
    FinalPolicies,
    final_policies_json,
    final_policies_markdown,
    read_final_policies,
)
from qtl.report.paper import beside_paper_markdown, paper_json
from qtl.report.paths import recorded_path
from qtl.report.record import EXPERIMENT_FILE
from qtl.report.reliability import reliability_json, reliability_markdown
from qtl.report.stability import stability_json, stability_markdown
from qtl.report.stats import (
    METRICS,
    JsonStat,
    cells_json,
    compliance_table,
    compliance_values,
    seed_values,
    stat_json,
)
from qtl.report.successes import success_json, success_markdown
from qtl.report.tables import REWARD_DIGITS, TITLES, markdown, table_numbers, tables_markdown

logger = logging.getLogger(__name__)

REPORT_DIR = "report"
REPORT_FILE = "report.md"
TABLES_FILE = "tables.json"
TRAIN_COMMAND = "qtl-train"
RECORD_HINT = ("record it with `qtl-report {root} --record-reference` (or rerun "
               "`qtl-experiment aircraft ...`, which reuses the finished runs)")

def tables_json(experiment: Experiment, final: FinalPolicies | None) -> dict[str, object]:
    """The numbers of Tables 1-6 (and of F1-F2 from ``final``, where evaluated) and of the runs behind them, for
    ``tables.json``."""
    values = seed_values(experiment)
    metrics: dict[str, dict[str, dict[str, JsonStat]]] = {}
    for metric in METRICS:
        metrics[metric] = cells_json(values[values["metric"] == metric])
    compliance = compliance_values(experiment)
    reference = experiment.reference
    return {
        "experiment": experiment.name,
        "root": recorded_path(experiment.root),
        "approaches": {a: approach_name(a) for a in experiment.approaches},
        "labels": experiment.labels,
        "sources": {str(seed): len(curve.returns) for seed, curve in experiment.sources.items()},
        "cells": {a: {label: {"seeds": cell.seeds, "episodes": cell.episodes, "truncated": cell.truncated,
                              "run_episodes": {str(s): n for s, n in sorted(cell.lengths.items())}}
                      for label, cell in by_label.items()}
                  for a, by_label in experiment.cells.items()},
        "left_out": list(experiment.left_out),
        **metrics,
        "compliance": {label: {"approach": row["approach"], **stat_json(row, compliance[
                           (compliance["approach"] == row["approach"]) & (compliance["label"] == label)])}
                       for label, row in compliance_table(experiment).iterrows()},
        "tables": {str(n): TITLES[n].format(label=experiment.labels[0]) for n in table_numbers(experiment)},
        "reference": None if reference is None else reference.to_dict(),
        "paper": paper_json(experiment),
        "successes": success_json(experiment),
        "stability": stability_json(experiment),
        "final_policies": None if final is None else final_policies_json(final),
        "reliability": reliability_json(experiment),
    }


def _command_of(run_dir: Path) -> str:
    """The ``qtl-train`` command line of a run, from its overrides."""
    overrides = run_overrides(run_dir)
    if overrides is None:
        return f"(no {OVERRIDES_FILE})"
    return " ".join([TRAIN_COMMAND, *map(shlex.quote, overrides)])


def _found_markdown(experiment: Experiment) -> str:
    """What the report was made from: source runs, approaches, labels, seeds and episodes per cell."""
    lines = [f"- Root: `{recorded_path(experiment.root)}`",
             f"- Experiment: {experiment.name or f'unnamed (no {EXPERIMENT_FILE})'}"]
    if experiment.sources:
        lengths = ", ".join(f"{SEED_PREFIX}{s}: {len(c.returns)}" for s, c in experiment.sources.items())
        lines.append(f"- Source runs: {len(experiment.sources)} ({lengths} episodes)")
    else:
        lines.append("- Source runs: none")
    lines.append("- Approaches: " + ", ".join(f"{approach_name(a)} (`{a}`)" for a in experiment.approaches))
    lines.append("- Targets: " + ", ".join(experiment.labels))
    if experiment.left_out:
        lines.append(f"- Left out, unfinished (fewer episodes than configured; a sweep still running): "
                     f"{len(experiment.left_out)} run(s): " + ", ".join(experiment.left_out))
    rows = []
    for approach, by_label in experiment.cells.items():
        for label, cell in by_label.items():
            note = ""
            if cell.truncated:
                runs = ", ".join(f"{SEED_PREFIX}{s}: {n}" for s, n in sorted(cell.lengths.items()))
                note = f"runs differ in length ({runs}): the common first {cell.episodes} episodes are used"
            chosen = {s: cell.curves[s].chosen_source() for s in cell.seeds}
            if any(k is not None for k in chosen.values()):  # runs of several sources: the one each chose
                picks = ", ".join(f"{SEED_PREFIX}{s}: {'-' if k is None else k}" for s, k in chosen.items())
                note = "; ".join(n for n in (note, f"source chosen by compliance ({picks})") if n)
            rows.append([f"{approach_name(approach)} / {label}", ", ".join(map(str, cell.seeds)), str(cell.episodes),
                         note])
    table = pd.DataFrame(rows, columns=["Approach / target", "Seeds", "Episodes", "Note"])
    return "\n".join(lines) + "\n\n" + markdown(table, text_columns=4)


def _commands_markdown(experiment: Experiment) -> str:
    """The commands of experiment.yaml, else the overrides of one run (the first seed) of every cell."""
    if experiment.commands:
        return f"From `{EXPERIMENT_FILE}`:\n\n```bash\n" + "\n".join(experiment.commands) + "\n```"
    runs = []
    if experiment.source_dirs:
        runs.append(next(iter(experiment.source_dirs.values())))
    runs += [cell.run_dirs[cell.seeds[0]] for by_label in experiment.cells.values() for cell in by_label.values()]
    lines = [f"- `{run.relative_to(experiment.root)}`: `{_command_of(run)}`" for run in runs]
    return (f"No `{EXPERIMENT_FILE}`: the overrides of one run per cell (the other seeds differ in `seed=`).\n\n"
            + "\n".join(lines))


def report_markdown(experiment: Experiment, figures: Sequence[Path], final: FinalPolicies | None) -> str:
    """``report.md``: what was found, Tables 1-6 (and beside the paper's), S1-S3, F1-F2 from ``final`` where the
    final policies were evaluated, S4-S5 where the runs logged θ, the learning curves, reliability counts and
    commands."""
    title = experiment.name or experiment.root.name
    png, *others = figures
    caption = "Learning curves: mean total reward per episode over seeds, error bars ±1 standard deviation."
    reference = experiment.reference
    beside = beside_paper_markdown(experiment)
    final_text = None if final is None else final_policies_markdown(final, experiment, recorded_path(experiment.root))
    stability = stability_markdown(experiment)
    if reference is not None:
        caption += f" Dashed: the {reference.name}'s total reward ({reference.total:.{REWARD_DIGITS}f})."
    sections = [
        f"# QTL-PILCO report: {title}",
        "## What was found\n\n" + _found_markdown(experiment),
        "## Tables\n\n" + "\n\n".join(tables_markdown(experiment)),
        *([] if beside is None else ["## Beside the paper\n\n" + beside]),
        "## Successes (not in the paper)\n\nFrom each episode's success test, over the same episodes as "
        "Tables 1-3.\n\n" + "\n\n".join(success_markdown(experiment)),
        *([] if final_text is None else ["## Final policies (not in the paper)\n\n" + final_text]),
        *([] if not stability else ["## Hyper-parameter stability (not in the paper)\n\nSection 5.1: QTL-PILCO "
                                    "keeps θ steadier than evidence maximisation alone.\n\n"
                                    + "\n\n".join(stability)]),
        f"## Learning curves\n\n![learning curves]({png.name})\n\n{caption} "
        + " ".join(f"[{p.suffix[1:].upper()}]({p.name})" for p in others),
        "## Reliability\n\nOver every run " + ("in the tables" if experiment.left_out else "found")
        + " (sources and targets), from each run's `health.csv`:\n\n"
        + reliability_markdown(experiment),
        "## Commands\n\n" + _commands_markdown(experiment),
    ]
    return "\n\n".join(sections) + "\n"


def write_report(root: str | Path, out_dir: str | Path | None = None, *, finished_only: bool = False) -> Path:
    """Write ``report.md``, ``tables.json`` and the learning-curve figure (Tables 1-6, Figs. 1-3); the report's path.

    ``out_dir`` defaults to ``<root>/report``. The autopilot line is read from ``experiment.yaml``, never computed
    here. ``finished_only``: leave out (and name) the runs with fewer episodes than configured. Raises ValueError
    when ``root`` has no target runs (none finished, with ``finished_only``) or a ``final_policies.json`` that
    ``qtl-evaluate`` did not write, before anything is written.
    """
    experiment = discover(root, finished_only=finished_only)
    final = read_final_policies(experiment)  # read once; a file it cannot read fails here, before anything is written
    out = experiment.root / REPORT_DIR if out_dir is None else Path(out_dir).expanduser().resolve()
    out.mkdir(parents=True, exist_ok=True)
    if flies_helicopter(experiment) and experiment.reference is None:
        logger.warning(
            "%s flies the helicopter but its %s records no autopilot reference: the figure has no autopilot line; %s",
            experiment.root, EXPERIMENT_FILE, RECORD_HINT.format(root=recorded_path(experiment.root)))
    figures = plot_learning_curves(experiment, out / FIGURE_STEM, experiment.reference)
    (out / TABLES_FILE).write_text(json.dumps(tables_json(experiment, final), indent=2, ensure_ascii=False) + "\n")
    report = out / REPORT_FILE
    report.write_text(report_markdown(experiment, figures, final), encoding="utf-8")
    logger.info("report written to %s", report)
    return report
