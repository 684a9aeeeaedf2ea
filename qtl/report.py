"""Section 5's tables and figures from an experiment directory (Tables 1-6, Figs. 1-3).

The layout read (made by the experiment presets through ``qtl-train``)::

    <root>/source/seed_<k>/                      source-task runs, one per seed
    <root>/target/<approach>/<label>/seed_<k>/   target runs; approach = a configs/approach/ preset
    <root>/experiment.yaml                       optional: {name: cartpole|mountaincar|aircraft, commands: [...]}

Every run directory holds ``metrics.csv`` (one row per episode) and ``.hydra/overrides.yaml``.
The seeds of a cell (one approach on one label) are compared on their common episodes: a cell
whose runs have different lengths (one was interrupted) is cut to its shortest run, and the
report says so. Every number is a mean over seeds ± its standard deviation (ddof = 1).

    >>> write_report("runs/cartpole")  # doctest: +SKIP
    PosixPath('runs/cartpole/report/report.md')
"""

from __future__ import annotations

import json
import logging
import math
import re
import shlex
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import yaml
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from omegaconf import DictConfig, OmegaConf

from envs import Autopilot
from qtl.metrics import (
    CONVERGED_FRACTION,
    FINAL_EPISODES,
    Curve,
    area_under_curve,
    final_performance,
    time_to_convergence,
)

logger = logging.getLogger(__name__)

# Approach presets (configs/approach/) and their names in the paper, in the order of its tables.
APPROACHES: dict[str, str] = {
    "pilco": "PILCO (γ = 0)",
    "hyperparameters_transfer": "Hyper-parameters transfer",
    "qtl_gamma_09": "QTL-PILCO γ = 0.9",
    "qtl_gamma_05": "QTL-PILCO γ = 0.5",
    "qtl_gamma_1": "QTL-PILCO γ = 1",
    "qtl_bayesian": "QTL-PILCO Bayesian",
    "policy_transfer": "Policy transfer",
}
COMPLIANCE_APPROACH = "qtl_bayesian"  # Table 4 reads this approach's runs where they have compliance

# The experiment directory.
SOURCE_DIR = "source"
TARGET_DIR = "target"
SEED_PREFIX = "seed_"
METRICS_FILE = "metrics.csv"
OVERRIDES_FILE = Path(".hydra") / "overrides.yaml"
CONFIG_FILE = Path(".hydra") / "config.yaml"
EXPERIMENT_FILE = "experiment.yaml"

# What the report writes.
REPORT_DIR = "report"
REPORT_FILE = "report.md"
TABLES_FILE = "tables.json"
FIGURE_STEM = "fig_learning_curves"
FIGURE_FORMATS = ("png", "pdf")
FIGURE_DPI = 150
PANEL_SIZE = (5.0, 3.6)  # inches per label
ERRORBAR_CAPSIZE = 2.0
REWARD_DIGITS = 2  # total rewards and areas, as the paper prints them
EPISODE_DIGITS = 1  # means of episode counts
COMPLIANCE_DIGITS = 2
MISSING = "—"
TRAIN_COMMAND = "qtl-train"

# The helicopter (Section 5.3, Fig. 3): the autopilot's return is drawn as a reference line.
HELICOPTER_ID = "qtl/Helicopter-v0"
AIRCRAFT_EXPERIMENT = "aircraft"
HELICOPTER_LABEL = "helicopter"
AUTOPILOT_NAME = "autopilot"

# A label is a prefix and a number (m1.5, p0.5) or anything else (helicopter).
NUMBERED_LABEL = re.compile(r"^(?P<prefix>[^\d+-]*)(?P<value>[+-]?\d+(?:\.\d*)?(?:[eE][+-]?\d+)?)$")

METRICS: dict[str, Callable[[Sequence[float]], float]] = {
    "final_performance": final_performance,  # Table 1
    "auc": area_under_curve,  # Tables 2 and 5
    "time_to_convergence": time_to_convergence,  # Tables 3 and 6
}
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


def approach_name(approach: str) -> str:
    """The paper's name of an approach preset (Tables 1-3, 5, 6); an unknown preset keeps its own."""
    return APPROACHES.get(approach, approach)


def approach_order(approach: str) -> tuple[int, str]:
    """Sort key: the paper's row order of Tables 1-3, unknown presets after it by name."""
    known = list(APPROACHES)
    return (known.index(approach), "") if approach in known else (len(known), approach)


def label_order(label: str) -> tuple[int, str, float, str]:
    """Sort key: labels numerically by their number within a prefix (m0.8 < m1.5 < m10), others after by name."""
    found = NUMBERED_LABEL.match(label)
    if found is None:
        return (1, label, 0.0, label)
    return (0, found["prefix"], float(found["value"]), label)


# ---- the experiment directory ------------------------------------------------------------------


@dataclass(frozen=True)
class Cell:
    """The runs of one approach on one target label, cut to their common episodes (a column of Tables 1-3)."""

    approach: str
    label: str
    curves: dict[int, Curve]  # seed -> the run's first `episodes` episodes
    lengths: dict[int, int]  # seed -> episodes in the run's metrics.csv
    run_dirs: dict[int, Path]

    @property
    def seeds(self) -> list[int]:
        """The seeds of this cell, ascending."""
        return sorted(self.curves)

    @property
    def episodes(self) -> int:
        """Episodes used: the common prefix of the seeds' runs."""
        return min(self.lengths.values())

    @property
    def truncated(self) -> bool:
        """Whether the runs have different lengths (so the longer ones were cut)."""
        return len(set(self.lengths.values())) > 1


@dataclass(frozen=True)
class Experiment:
    """An experiment directory: source runs, target cells per approach and label, and its record."""

    root: Path
    name: str | None
    commands: list[str]  # from experiment.yaml, empty without one
    sources: dict[int, Curve]  # seed -> source run
    source_dirs: dict[int, Path]
    cells: dict[str, dict[str, Cell]]  # approach -> label -> cell; approaches in table order

    @property
    def approaches(self) -> list[str]:
        """Approach presets present, in the paper's row order."""
        return list(self.cells)

    @property
    def labels(self) -> list[str]:
        """Target labels present in any approach, sorted numerically where possible."""
        return sorted({label for by_label in self.cells.values() for label in by_label}, key=label_order)

    @property
    def curves(self) -> dict[str, dict[str, dict[int, Curve]]]:
        """{approach: {label: {seed: Curve}}}, each curve cut to its cell's common episodes."""
        return {a: {lab: dict(cell.curves) for lab, cell in by_label.items()} for a, by_label in self.cells.items()}

    def cell(self, approach: str, label: str) -> Cell | None:
        """The cell of ``approach`` on ``label``, or None when that combination was not run."""
        return self.cells.get(approach, {}).get(label)


def _seed_runs(folder: Path) -> dict[int, tuple[Path, Curve]]:
    """{seed: (run dir, whole curve)} of the ``seed_<k>`` folders under ``folder`` with at least one episode."""
    runs: dict[int, tuple[Path, Curve]] = {}
    if not folder.is_dir():
        return runs
    for run_dir in folder.iterdir():
        suffix = run_dir.name.removeprefix(SEED_PREFIX)
        if not (run_dir.is_dir() and run_dir.name.startswith(SEED_PREFIX) and suffix.isdigit()):
            continue
        if not (run_dir / METRICS_FILE).is_file():
            logger.warning("%s has no %s: skipped", run_dir, METRICS_FILE)
            continue
        curve = Curve.read(run_dir)
        if curve.returns:
            runs[int(suffix)] = (run_dir, curve)
        else:
            logger.warning("%s has no episode yet: skipped", run_dir)
    return dict(sorted(runs.items()))


def _read_cell(approach: str, label: str, runs: dict[int, tuple[Path, Curve]]) -> Cell:
    """The cell of these runs, the longer ones re-read up to the shortest run's length."""
    lengths = {seed: len(curve.returns) for seed, (_, curve) in runs.items()}
    common = min(lengths.values())
    if len(set(lengths.values())) > 1:
        logger.warning("%s / %s: runs have %s episodes; the common first %d are used", approach, label,
                       sorted(lengths.values()), common)
    curves = {seed: curve if lengths[seed] == common else Curve.read(run_dir, common)
              for seed, (run_dir, curve) in runs.items()}
    return Cell(approach, label, curves, lengths, {seed: run_dir for seed, (run_dir, _) in runs.items()})


def _read_record(root: Path) -> tuple[str | None, list[str]]:
    """The experiment's name and commands from ``experiment.yaml`` (None and [] without one)."""
    path = root / EXPERIMENT_FILE
    if not path.is_file():
        return None, []
    record = yaml.safe_load(path.read_text()) or {}
    if not isinstance(record, dict):
        raise ValueError(f"{path}: expected a mapping with 'name' and 'commands', got {type(record).__name__}")
    name = record.get("name")
    return (None if name is None else str(name)), [str(c) for c in record.get("commands") or []]


def discover(root: str | Path) -> Experiment:
    """Read every run of an experiment directory (the data behind Tables 1-6 and Figs. 1-3)."""
    root = Path(root).expanduser().resolve()
    targets = root / TARGET_DIR
    cells: dict[str, dict[str, Cell]] = {}
    approach_dirs = [p for p in targets.iterdir() if p.is_dir()] if targets.is_dir() else []
    for approach_dir in sorted(approach_dirs, key=lambda p: approach_order(p.name)):
        by_label: dict[str, Cell] = {}
        for label_dir in sorted((p for p in approach_dir.iterdir() if p.is_dir()), key=lambda p: label_order(p.name)):
            runs = _seed_runs(label_dir)
            if runs:
                by_label[label_dir.name] = _read_cell(approach_dir.name, label_dir.name, runs)
        if by_label:
            cells[approach_dir.name] = by_label
    if not cells:
        expected = targets / "<approach>" / "<label>" / f"{SEED_PREFIX}<k>" / METRICS_FILE
        raise ValueError(f"{root}: no target runs (expected {expected})")
    sources = _seed_runs(root / SOURCE_DIR)
    name, commands = _read_record(root)
    return Experiment(
        root=root,
        name=name,
        commands=commands,
        sources={seed: curve for seed, (_, curve) in sources.items()},
        source_dirs={seed: run_dir for seed, (run_dir, _) in sources.items()},
        cells=cells,
    )


# ---- numbers -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Stat:
    """One number over seeds: mean ± standard deviation (ddof = 1), the form of every cell of Tables 1-6."""

    per_seed: dict[int, float]

    @property
    def n(self) -> int:
        """Number of seeds."""
        return len(self.per_seed)

    @property
    def mean(self) -> float:
        """Mean over seeds."""
        return float(np.mean(list(self.per_seed.values())))

    @property
    def std(self) -> float | None:
        """Sample standard deviation over seeds (ddof = 1); None for a single seed."""
        return float(np.std(list(self.per_seed.values()), ddof=1)) if self.n > 1 else None

    def text(self, digits: int, whole: bool = False) -> str:
        """``mean ± std`` to ``digits`` decimals, the bare value for one seed (an integer if ``whole``)."""
        if self.std is None:
            return str(round(self.mean)) if whole else f"{self.mean:.{digits}f}"
        return f"{self.mean:.{digits}f} ± {self.std:.{digits}f}"

    def to_json(self) -> dict[str, Any]:
        """Mean, std, number of seeds and the per-seed values, for ``tables.json``."""
        return {"mean": self.mean, "std": self.std, "n": self.n,
                "per_seed": {str(seed): value for seed, value in sorted(self.per_seed.items())}}


def cell_stat(cell: Cell, metric: str) -> Stat:
    """A learning-curve metric of :data:`METRICS` over the seeds of one cell (a cell of Tables 1-3, 5, 6)."""
    summary = METRICS[metric]
    return Stat({seed: float(summary(curve.returns)) for seed, curve in cell.curves.items()})


def metric_table(experiment: Experiment, metric: str) -> dict[str, dict[str, Stat]]:
    """{approach: {label: Stat}} of one metric: Table 1 (final_performance), 2 (auc) or 3 (time_to_convergence)."""
    return {a: {label: cell_stat(cell, metric) for label, cell in by_label.items()}
            for a, by_label in experiment.cells.items()}


def last_compliance(cell: Cell) -> Stat | None:
    """Task compliance of the last episode over the seeds whose runs computed one (Table 4); None if none did."""
    values = {seed: curve.compliance[-1] for seed, curve in cell.curves.items() if not math.isnan(curve.compliance[-1])}
    return Stat(values) if values else None


def compliance_table(experiment: Experiment) -> dict[str, tuple[str, Stat]]:
    """{label: (approach, Stat)} of Table 4: QTL-PILCO Bayesian where it has compliance, else the first that has."""
    table: dict[str, tuple[str, Stat]] = {}
    preferred = [COMPLIANCE_APPROACH] + [a for a in experiment.approaches if a != COMPLIANCE_APPROACH]
    for label in experiment.labels:
        for approach in preferred:
            cell = experiment.cell(approach, label)
            stat = None if cell is None else last_compliance(cell)
            if stat is not None:
                table[label] = (approach, stat)
                break
    return table


# ---- markdown ----------------------------------------------------------------------------------


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]], text_columns: int = 1) -> str:
    """A markdown table, its first ``text_columns`` columns left-aligned and the (numeric) others right-aligned."""
    rule = ["---" if i < text_columns else "---:" for i in range(len(header))]
    lines = ["| " + " | ".join(header) + " |", "| " + " | ".join(rule) + " |"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def _seed_counts(counts: Sequence[int]) -> str:
    """The seeds column: one number when every cell of the row has as many seeds, else one per cell."""
    return str(counts[0]) if len(set(counts)) == 1 else ", ".join(map(str, counts))


def _table_heading(number: int, **fields: str) -> str:
    """``**Table n.** title`` as the paper captions its tables."""
    return f"**Table {number}.** {TITLES[number].format(**fields)}"


def metric_markdown(experiment: Experiment, number: int, metric: str) -> str:
    """Table 1, 2 or 3 in markdown: rows approaches, columns labels, ``mean ± std`` cells, seeds per row."""
    table = metric_table(experiment, metric)
    whole = metric == "time_to_convergence"
    digits = EPISODE_DIGITS if whole else REWARD_DIGITS
    labels = experiment.labels
    rows = []
    for approach, by_label in table.items():
        cells = [by_label[label].text(digits, whole) if label in by_label else MISSING for label in labels]
        rows.append([approach_name(approach), *cells, _seed_counts([s.n for s in by_label.values()])])
    return _table_heading(number) + "\n\n" + markdown_table(["Approach", *labels, "Seeds"], rows)


def compliance_markdown(experiment: Experiment) -> str | None:
    """Table 4 in markdown: one row per label with task compliance; None when no run computed compliance."""
    table = compliance_table(experiment)
    if not table:
        return None
    rows = [[label, approach_name(approach), stat.text(COMPLIANCE_DIGITS), str(stat.n)]
            for label, (approach, stat) in table.items()]
    return _table_heading(4) + "\n\n" + markdown_table(["Target", "Approach", "Task compliance", "Seeds"], rows, 2)


def single_label_markdown(experiment: Experiment) -> tuple[str, str]:
    """Tables 5 (area under the curve) and 6 (time to convergence (final performance)) of a one-label experiment."""
    (label,) = experiment.labels
    auc_rows, convergence_rows = [], []
    for approach in experiment.approaches:
        cell = experiment.cell(approach, label)
        assert cell is not None  # one label: every approach present has it
        auc = cell_stat(cell, "auc")
        ttc, final = cell_stat(cell, "time_to_convergence"), cell_stat(cell, "final_performance")
        auc_rows.append([approach_name(approach), auc.text(REWARD_DIGITS), str(auc.n)])
        convergence_rows.append([approach_name(approach),
                                 f"{ttc.text(EPISODE_DIGITS, whole=True)} ({final.text(REWARD_DIGITS)})", str(ttc.n)])
    table5 = _table_heading(5, label=label) + "\n\n" + markdown_table(["Approach", "Area under curve", "Seeds"],
                                                                       auc_rows)
    table6 = _table_heading(6) + "\n\n" + markdown_table(
        ["Approach", "Time to convergence (final performance)", "Seeds"], convergence_rows)
    return table5, table6


def run_overrides(run_dir: Path) -> list[str] | None:
    """The Hydra overrides a run was made with (``.hydra/overrides.yaml``), or None without that file."""
    path = run_dir / OVERRIDES_FILE
    if not path.is_file():
        return None
    return [str(o) for o in yaml.safe_load(path.read_text()) or []]


def _command_of(run_dir: Path) -> str:
    """The ``qtl-train`` command line of a run, from its overrides."""
    overrides = run_overrides(run_dir)
    if overrides is None:
        return f"(no {OVERRIDES_FILE})"
    return " ".join([TRAIN_COMMAND, *map(shlex.quote, overrides)])


def _found_markdown(experiment: Experiment) -> str:
    """What the report was made from: source runs, approaches, labels, seeds and episodes per cell."""
    lines = [f"- Root: `{experiment.root}`", f"- Experiment: {experiment.name or 'unnamed (no experiment.yaml)'}"]
    if experiment.sources:
        lengths = ", ".join(f"{SEED_PREFIX}{s}: {len(c.returns)}" for s, c in experiment.sources.items())
        lines.append(f"- Source runs: {len(experiment.sources)} ({lengths} episodes)")
    else:
        lines.append("- Source runs: none")
    lines.append("- Approaches: " + ", ".join(f"{approach_name(a)} (`{a}`)" for a in experiment.approaches))
    lines.append("- Targets: " + ", ".join(experiment.labels))
    rows = []
    for approach, by_label in experiment.cells.items():
        for label, cell in by_label.items():
            note = ""
            if cell.truncated:
                runs = ", ".join(f"{SEED_PREFIX}{s}: {n}" for s, n in sorted(cell.lengths.items()))
                note = f"runs differ in length ({runs}): the common first {cell.episodes} episodes are used"
            rows.append([f"{approach_name(approach)} / {label}", ", ".join(map(str, cell.seeds)), str(cell.episodes),
                         note])
    table = markdown_table(["Approach / target", "Seeds", "Episodes", "Note"], rows, text_columns=4)
    return "\n".join(lines) + "\n\n" + table


def _commands_markdown(experiment: Experiment) -> str:
    """The commands of experiment.yaml, else the overrides of one run (the first seed) of every cell."""
    if experiment.commands:
        return "From `experiment.yaml`:\n\n```bash\n" + "\n".join(experiment.commands) + "\n```"
    runs = []
    if experiment.source_dirs:
        runs.append(next(iter(experiment.source_dirs.values())))
    runs += [cell.run_dirs[cell.seeds[0]] for by_label in experiment.cells.values() for cell in by_label.values()]
    lines = [f"- `{run.relative_to(experiment.root)}`: `{_command_of(run)}`" for run in runs]
    return "No `experiment.yaml`: the overrides of one run per cell (the other seeds differ in `seed=`).\n\n" + \
        "\n".join(lines)


def tables_markdown(experiment: Experiment) -> list[str]:
    """Every table of the report in markdown: Tables 1-3, Table 4 if any compliance, Tables 5-6 for one label."""
    tables = [metric_markdown(experiment, number, metric)
              for number, metric in ((1, "final_performance"), (2, "auc"), (3, "time_to_convergence"))]
    compliance = compliance_markdown(experiment)
    if compliance is not None:
        tables.append(compliance)
    if len(experiment.labels) == 1:
        tables += single_label_markdown(experiment)
    return tables


# ---- figures -----------------------------------------------------------------------------------


def legend_entries(axes: Any) -> tuple[list[Any], list[str]]:
    """Handles and labels of every panel, each label once in order of appearance: one legend for all panels."""
    entries: dict[str, Any] = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            entries.setdefault(label, handle)
    return list(entries.values()), list(entries)


def plot_learning_curves(experiment: Experiment, stem: Path, reference: tuple[str, float] | None = None) -> list[Path]:
    """Figs. 1-3: mean total reward per episode ±1 std over seeds, one panel per label; saved as ``stem``.png/.pdf.

    ``reference`` (name, total reward) adds a horizontal line to every panel (the autopilot of Fig. 3).
    """
    labels = experiment.labels
    fig = Figure(figsize=(PANEL_SIZE[0] * len(labels), PANEL_SIZE[1]), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(labels), sharey=True, squeeze=False)[0]
    for ax, label in zip(axes, labels, strict=True):
        for approach in experiment.approaches:
            cell = experiment.cell(approach, label)
            if cell is None:
                continue
            returns = np.array([cell.curves[seed].returns for seed in cell.seeds])  # seeds x episodes
            std = returns.std(axis=0, ddof=1) if len(returns) > 1 else None
            ax.errorbar(np.arange(cell.episodes), returns.mean(axis=0), yerr=std, capsize=ERRORBAR_CAPSIZE,
                        marker=".", color=f"C{experiment.approaches.index(approach)}", label=approach_name(approach))
        if reference is not None:
            ax.axhline(reference[1], color="k", linestyle="--", label=reference[0])
        ax.set_title(label)
        ax.set_xlabel("episode")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("total reward")
    axes[0].legend(*legend_entries(axes), fontsize="small")
    paths = [stem.with_suffix(f".{fmt}") for fmt in FIGURE_FORMATS]
    for path in paths:
        fig.savefig(path, dpi=FIGURE_DPI)
    return paths


# ---- the helicopter's autopilot ----------------------------------------------------------------


def autopilot_return(env_kwargs: dict[str, Any] | None = None, seed: int = 0) -> float:
    """Total reward of one helicopter episode flown by the env's :class:`envs.Autopilot` (the reference of Fig. 3).

    ``env_kwargs`` are ``qtl/Helicopter-v0`` constructor kwargs (an ``id`` key, as in ``task.env``, is ignored).
    """
    kwargs = {key: value for key, value in (env_kwargs or {}).items() if key != "id"}
    env = gymnasium.make(HELICOPTER_ID, **kwargs)
    try:
        pilot = Autopilot(env)
        obs, _ = env.reset(seed=seed)
        total, done = 0.0, False
        while not done:
            obs, reward, terminated, truncated, _ = env.step(pilot(obs))
            total += float(reward)
            done = terminated or truncated
    finally:
        env.close()
    return total


def _flies_helicopter(experiment: Experiment) -> bool:
    """Whether the report draws the autopilot line: an aircraft experiment or a helicopter target (Fig. 3)."""
    return experiment.name == AIRCRAFT_EXPERIMENT or HELICOPTER_LABEL in experiment.labels


def _helicopter_kwargs(experiment: Experiment) -> dict[str, Any]:
    """`task.env` of the first target run whose `.hydra/config.yaml` flies the helicopter (Fig. 3); {} if none."""
    for by_label in experiment.cells.values():
        for cell in by_label.values():
            path = cell.run_dirs[cell.seeds[0]] / CONFIG_FILE
            env = OmegaConf.select(OmegaConf.load(path), "task.env") if path.is_file() else None
            if isinstance(env, DictConfig) and env.get("id") == HELICOPTER_ID:
                return OmegaConf.to_container(env, resolve=True)  # type: ignore[return-value]
    logger.warning("no target run records a %s config: the autopilot flies the default helicopter", HELICOPTER_ID)
    return {}


# ---- the report --------------------------------------------------------------------------------


def tables_json(experiment: Experiment, reference: tuple[str, float] | None = None) -> dict[str, Any]:
    """The numbers of Tables 1-6 and of the runs behind them, for ``tables.json``."""
    single = len(experiment.labels) == 1
    tables = [1, 2, 3] + ([4] if compliance_table(experiment) else []) + ([5, 6] if single else [])
    return {
        "experiment": experiment.name,
        "root": str(experiment.root),
        "approaches": {a: approach_name(a) for a in experiment.approaches},
        "labels": experiment.labels,
        "sources": {str(seed): len(curve.returns) for seed, curve in experiment.sources.items()},
        "cells": {a: {label: {"seeds": cell.seeds, "episodes": cell.episodes, "truncated": cell.truncated,
                              "run_episodes": {str(s): n for s, n in sorted(cell.lengths.items())}}
                      for label, cell in by_label.items()}
                  for a, by_label in experiment.cells.items()},
        **{metric: {a: {label: stat.to_json() for label, stat in by_label.items()}
                    for a, by_label in metric_table(experiment, metric).items()}
           for metric in METRICS},
        "compliance": {label: {"approach": approach, **stat.to_json()}
                       for label, (approach, stat) in compliance_table(experiment).items()},
        "tables": {str(n): TITLES[n].format(label=experiment.labels[0]) for n in tables},
        "reference": None if reference is None else {"name": reference[0], "return": reference[1]},
    }


def report_markdown(experiment: Experiment, figures: Sequence[Path], reference: tuple[str, float] | None) -> str:
    """``report.md``: what was found, Tables 1-6, the learning-curve figure and the commands that made the runs."""
    title = experiment.name or experiment.root.name
    png, *others = figures
    caption = "Learning curves: mean total reward per episode over seeds, error bars ±1 standard deviation."
    if reference is not None:
        caption += f" Dashed: the {reference[0]}'s total reward ({reference[1]:.{REWARD_DIGITS}f})."
    sections = [
        f"# QTL-PILCO report: {title}",
        "## What was found\n\n" + _found_markdown(experiment),
        "## Tables\n\n" + "\n\n".join(tables_markdown(experiment)),
        f"## Learning curves\n\n![learning curves]({png.name})\n\n{caption} "
        + " ".join(f"[{p.suffix[1:].upper()}]({p.name})" for p in others),
        "## Commands\n\n" + _commands_markdown(experiment),
    ]
    return "\n\n".join(sections) + "\n"


def write_report(root: str | Path, out_dir: str | Path | None = None) -> Path:
    """Write ``report.md``, ``tables.json`` and the learning-curve figure (Tables 1-6, Figs. 1-3); the report's path.

    ``out_dir`` defaults to ``<root>/report``. Raises ValueError when ``root`` has no target runs.
    """
    experiment = discover(root)
    out = experiment.root / REPORT_DIR if out_dir is None else Path(out_dir).expanduser().resolve()
    out.mkdir(parents=True, exist_ok=True)
    reference = None
    if _flies_helicopter(experiment):
        reference = (AUTOPILOT_NAME, autopilot_return(_helicopter_kwargs(experiment)))
    figures = plot_learning_curves(experiment, out / FIGURE_STEM, reference)
    (out / TABLES_FILE).write_text(json.dumps(tables_json(experiment, reference), indent=2, ensure_ascii=False) + "\n")
    report = out / REPORT_FILE
    report.write_text(report_markdown(experiment, figures, reference), encoding="utf-8")
    logger.info("report written to %s", report)
    return report
