"""A finished experiment's small files, copied elsewhere: what its report is rebuilt from, without the heavy ones.

A run leaves its configuration, three CSVs, its checkpoints, TensorBoard events and a log. The report
(:func:`~qtl.report.write_report`) reads only the configuration (``.hydra/config.yaml`` for the episodes a run
asks for, ``.hydra/overrides.yaml`` for the swept value and the commands) and the CSVs; ``--status`` reads
``timings.csv`` as well. So an export holds, with the experiment's layout:

- per run: :data:`RUN_FILES`;
- per experiment: :data:`EXPERIMENT_FILES` and the report in ``report/`` (:data:`REPORT_FILES`), where present.

Checkpoints, events, logs, Hydra's own ``hydra.yaml`` and ``multirun.yaml`` stay behind: rerunning the sweep with
the same seeds makes them again. An export never overwrites (a destination that exists must be empty) and holds
finished runs only: an unfinished run is refused, or, with ``finished_only``, left out.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from qtl.recorder import HEALTH_FILE, METRICS_FILE, TIMINGS_FILE
from qtl.report.discover import CONFIG_FILE, OVERRIDES_FILE, discover
from qtl.report.figures import FIGURE_FORMATS, FIGURE_STEM
from qtl.report.final_policies import FINAL_POLICIES_FILE
from qtl.report.record import EXPERIMENT_FILE
from qtl.report.write import REPORT_DIR, REPORT_FILE, TABLES_FILE

RUN_FILES: tuple[Path, ...] = (CONFIG_FILE, OVERRIDES_FILE, Path(METRICS_FILE), Path(TIMINGS_FILE),
                               Path(HEALTH_FILE))
EXPERIMENT_FILES: tuple[Path, ...] = (Path(EXPERIMENT_FILE), Path(FINAL_POLICIES_FILE))
REPORT_FILES: tuple[Path, ...] = tuple(Path(REPORT_DIR) / name for name in (
    REPORT_FILE, TABLES_FILE, *(f"{FIGURE_STEM}.{fmt}" for fmt in FIGURE_FORMATS)))


def export_files(root: str | os.PathLike, *, finished_only: bool = False) -> list[Path]:
    """The files of ``root`` an export copies, relative to ``root``, in order: the experiment's, then each run's.

    Raises ValueError, in one line, when ``root`` holds no (finished) target run, or an unfinished run and not
    ``finished_only``.
    """
    experiment = discover(root, finished_only=True)
    if experiment.left_out and not finished_only:
        raise ValueError(f"{experiment.root}: {len(experiment.left_out)} unfinished run(s), "
                         f"{', '.join(experiment.left_out)}: finish the sweep, or export the finished runs only "
                         "(--finished-only)")
    runs = [*experiment.source_dirs.values(), *experiment.run_dirs()]
    found = [name for name in (*EXPERIMENT_FILES, *REPORT_FILES) if (experiment.root / name).is_file()]
    for run_dir in runs:
        found += [run_dir.relative_to(experiment.root) / name for name in RUN_FILES if (run_dir / name).is_file()]
    return found


def export(root: str | os.PathLike, dest: str | os.PathLike, *, finished_only: bool = False) -> list[Path]:
    """Copy the small files of the experiment ``root`` (:func:`export_files`) into ``dest``, with the same layout;
    the files written.

    Everything is checked before anything is written: raises ValueError, in one line, when ``dest`` exists and is
    not an empty folder, or as :func:`export_files` does.
    """
    dest = Path(dest).expanduser()
    if dest.exists() and not (dest.is_dir() and not any(dest.iterdir())):
        raise ValueError(f"{dest} exists and is not an empty folder: an export never overwrites; give a new folder")
    source = Path(root).expanduser().resolve()
    names = export_files(source, finished_only=finished_only)
    written = []
    for name in names:
        target = dest / name
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(source / name, target)  # a link (a symlinked source/) is copied as the file it points to
        written.append(target)
    return written
