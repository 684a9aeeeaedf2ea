"""Figs. 1-3: learning curves, mean total reward per episode ±1 std over seeds, one panel per target label."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np
from matplotlib.artist import Artist
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from qtl.report.approaches import approach_name
from qtl.report.discover import Experiment
from qtl.report.record import Reference
from qtl.report.stats import episode_stats

FIGURE_STEM = "fig_learning_curves"
FIGURE_FORMATS = ("png", "pdf")
FIGURE_DPI = 150
PANEL_SIZE = (5.0, 3.6)  # inches per label
ERRORBAR_CAPSIZE = 2.0


def legend_entries(axes: Iterable[Axes]) -> tuple[list[Artist], list[str]]:
    """Handles and labels of every panel, each label once in order of appearance: one legend for all panels."""
    entries: dict[str, Artist] = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            entries.setdefault(label, handle)
    return list(entries.values()), list(entries)


def plot_learning_curves(experiment: Experiment, stem: Path, reference: Reference | None = None) -> list[Path]:
    """Figs. 1-3, saved as ``stem``.png/.pdf; ``reference`` adds its total reward as a dashed line to every panel."""
    labels = experiment.labels
    fig = Figure(figsize=(PANEL_SIZE[0] * len(labels), PANEL_SIZE[1]), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, len(labels), sharey=True, squeeze=False)[0]
    for ax, label in zip(axes, labels, strict=True):
        for index, approach in enumerate(experiment.approaches):
            cell = experiment.cell(approach, label)
            if cell is None:
                continue
            stats = episode_stats(cell)
            std = stats["std"].to_numpy() if len(cell.seeds) > 1 else None
            ax.errorbar(np.arange(cell.episodes), stats["mean"].to_numpy(), yerr=std, capsize=ERRORBAR_CAPSIZE,
                        marker=".", color=f"C{index}", label=approach_name(approach))
        if reference is not None:
            ax.axhline(reference.total, color="k", linestyle="--", label=reference.name)
        ax.set_title(label)
        ax.set_xlabel("episode")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("total reward")
    axes[0].legend(*legend_entries(axes), fontsize="small")
    paths = [stem.with_suffix(f".{fmt}") for fmt in FIGURE_FORMATS]
    for path in paths:
        fig.savefig(path, dpi=FIGURE_DPI)
    return paths
