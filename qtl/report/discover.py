"""An experiment directory read: its source runs, its target cells per approach and label, and its record.

The layout (made by the experiment presets through ``qtl-train``)::

    <root>/source/seed_<k>/                      source-task runs, one per seed
    <root>/target/<approach>/<label>/seed_<k>/   target runs; approach = a configs/approach/ preset
    <root>/experiment.yaml                       optional: name, commands, reference (see qtl.report.record)

Every run directory holds ``metrics.csv`` (one row per episode) and ``.hydra/overrides.yaml``.
The seeds of a cell (one approach on one label) are compared on their common episodes: a cell
whose runs have different lengths (one was interrupted) is cut to its shortest run. With ``finished_only``
(a sweep still running), runs with fewer episodes than their configuration asks for are left out instead, and named.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import yaml

from qtl.metrics import Curve
from qtl.recorder import METRICS_FILE
from qtl.report.approaches import approach_order
from qtl.report.record import ExperimentRecord, Reference

logger = logging.getLogger(__name__)

SOURCE_DIR = "source"
TARGET_DIR = "target"
SEED_PREFIX = "seed_"
OVERRIDES_FILE = Path(".hydra") / "overrides.yaml"
CONFIG_FILE = Path(".hydra") / "config.yaml"

# A label is a prefix and a number (m1.5, p0.5) or anything else (helicopter).
NUMBERED_LABEL = re.compile(r"^(?P<prefix>[^\d+-]*)(?P<value>[+-]?\d+(?:\.\d*)?(?:[eE][+-]?\d+)?)$")


def label_order(label: str) -> tuple[int, str, float, str]:
    """Sort key: labels numerically by their number within a prefix (m0.8 < m1.5 < m10), others after by name."""
    found = NUMBERED_LABEL.match(label)
    if found is None:
        return (1, label, 0.0, label)
    return (0, found["prefix"], float(found["value"]), label)


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
    reference: Reference | None = None  # from experiment.yaml: the line drawn beside the curves (Fig. 3)
    left_out: tuple[str, ...] = ()  # unfinished runs left out (``finished_only``): "<run> (k of K episodes)"

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

    def run_dirs(self) -> list[Path]:
        """Every target run directory, cell by cell in table order, seeds ascending."""
        return [cell.run_dirs[seed] for by_label in self.cells.values() for cell in by_label.values()
                for seed in cell.seeds]


def configured_episodes(run_dir: Path) -> int | None:
    """Episodes the run's configuration asks for (random + learned), from ``.hydra/config.yaml``; None without it."""
    path = run_dir / CONFIG_FILE
    if not path.is_file():
        return None
    cfg = yaml.safe_load(path.read_text()) or {}
    if "episodes" not in cfg:
        return None
    return int(cfg.get("random_episodes", 1)) + int(cfg["episodes"])


def _seed_runs(folder: Path, left_out: list[tuple[Path, int, int]] | None = None) -> dict[int, tuple[Path, Curve]]:
    """{seed: (run dir, whole curve)} of the ``seed_<k>`` folders under ``folder`` with at least one episode.

    With ``left_out`` given (``finished_only``), a run with fewer episodes than configured is skipped and added
    there as (run dir, episodes made, episodes configured).
    """
    runs: dict[int, tuple[Path, Curve]] = {}
    if not folder.is_dir():
        return runs
    for run_dir in sorted(folder.iterdir()):
        suffix = run_dir.name.removeprefix(SEED_PREFIX)
        if not (run_dir.is_dir() and run_dir.name.startswith(SEED_PREFIX) and suffix.isdigit()):
            continue
        if not (run_dir / METRICS_FILE).is_file():
            logger.warning("%s has no %s: skipped", run_dir, METRICS_FILE)
            continue
        curve = Curve.read(run_dir)
        configured = configured_episodes(run_dir) if left_out is not None else None
        if configured is not None and len(curve.returns) < configured:
            left_out.append((run_dir, len(curve.returns), configured))
        elif curve.returns:
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


def discover(root: str | Path, *, finished_only: bool = False) -> Experiment:
    """Read every run of an experiment directory (the data behind Tables 1-6 and Figs. 1-3).

    ``finished_only``: leave out the runs that have fewer episodes than their configuration asks for (a sweep
    still running, or an interrupted run), named in ``Experiment.left_out``, instead of cutting their cells.
    """
    root = Path(root).expanduser().resolve()
    targets = root / TARGET_DIR
    left_out: list[tuple[Path, int, int]] | None = [] if finished_only else None
    cells: dict[str, dict[str, Cell]] = {}
    approach_dirs = [p for p in targets.iterdir() if p.is_dir()] if targets.is_dir() else []
    for approach_dir in sorted(approach_dirs, key=lambda p: approach_order(p.name)):
        by_label: dict[str, Cell] = {}
        for label_dir in sorted((p for p in approach_dir.iterdir() if p.is_dir()), key=lambda p: label_order(p.name)):
            runs = _seed_runs(label_dir, left_out)
            if runs:
                by_label[label_dir.name] = _read_cell(approach_dir.name, label_dir.name, runs)
        if by_label:
            cells[approach_dir.name] = by_label
    if not cells:
        expected = targets / "<approach>" / "<label>" / f"{SEED_PREFIX}<k>" / METRICS_FILE
        which = "finished target runs" if finished_only else "target runs"
        raise ValueError(f"{root}: no {which} (expected {expected})")
    sources = _seed_runs(root / SOURCE_DIR, left_out)
    record = ExperimentRecord.read(root)
    return Experiment(
        root=root,
        name=record.name,
        commands=record.commands,
        sources={seed: curve for seed, (_, curve) in sources.items()},
        source_dirs={seed: run_dir for seed, (run_dir, _) in sources.items()},
        cells=cells,
        reference=record.reference,
        left_out=tuple(f"{run_dir.relative_to(root)} ({made} of {configured} episodes)"
                       for run_dir, made, configured in left_out or []),
    )


def run_overrides(run_dir: Path) -> list[str] | None:
    """The Hydra overrides a run was made with (``.hydra/overrides.yaml``), or None without that file."""
    path = run_dir / OVERRIDES_FILE
    if not path.is_file():
        return None
    return [str(o) for o in yaml.safe_load(path.read_text()) or []]
