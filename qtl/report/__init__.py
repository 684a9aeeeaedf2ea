"""Section 5's tables and figures from an experiment directory (Tables 1-6, Figs. 1-3).

``discover`` reads the runs (:mod:`~qtl.report.discover`), :mod:`~qtl.report.stats` computes mean ± std
over seeds with pandas, :mod:`~qtl.report.tables` and :mod:`~qtl.report.figures` draw them,
:mod:`~qtl.report.paper` holds the paper's published numbers to set beside them,
:mod:`~qtl.report.autopilot` records the helicopter's reference line when the experiment runs,
``write_report`` puts ``report.md``, ``tables.json`` and the figure together, ``export`` copies the small files
a finished experiment's report is rebuilt from (:mod:`~qtl.report.export`), and :mod:`~qtl.report.cli` is
``qtl-report``. Recorded paths are relative to the repository (:mod:`~qtl.report.paths`).
"""

from __future__ import annotations

from qtl.report.approaches import (
    APPROACHES,
    COMPLIANCE_APPROACH,
    DEFAULT_APPROACH,
    approach_name,
    approach_order,
    approach_overrides,
)
from qtl.report.autopilot import autopilot_return, flies_helicopter, record_reference
from qtl.report.discover import SEED_PREFIX, SOURCE_DIR, TARGET_DIR, Cell, Experiment, discover, label_order
from qtl.report.export import export, export_files
from qtl.report.figures import legend_entries, plot_learning_curves
from qtl.report.paths import recorded_path
from qtl.report.record import EXPERIMENT_FILE, ExperimentRecord, Reference
from qtl.report.stats import compliance_table, metric_table
from qtl.report.tables import tables_markdown
from qtl.report.write import REPORT_DIR, REPORT_FILE, TABLES_FILE, tables_json, write_report

__all__ = [
    "APPROACHES",
    "COMPLIANCE_APPROACH",
    "DEFAULT_APPROACH",
    "EXPERIMENT_FILE",
    "REPORT_DIR",
    "REPORT_FILE",
    "SEED_PREFIX",
    "SOURCE_DIR",
    "TABLES_FILE",
    "TARGET_DIR",
    "Cell",
    "Experiment",
    "ExperimentRecord",
    "Reference",
    "approach_name",
    "approach_order",
    "approach_overrides",
    "autopilot_return",
    "compliance_table",
    "discover",
    "export",
    "export_files",
    "flies_helicopter",
    "label_order",
    "legend_entries",
    "metric_table",
    "plot_learning_curves",
    "record_reference",
    "recorded_path",
    "tables_json",
    "tables_markdown",
    "write_report",
]
