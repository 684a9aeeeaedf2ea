"""Tables S4-S5 (not in the paper): how far the model's hyper-parameters θ move from one episode to the next.

Section 5.1 holds that QTL-PILCO stabilises θ: evidence maximisation alone (PILCO) can change θ drastically in
the first episodes, from poor samples, where QTL-PILCO incorporates the target's θ_p gradually (Eq. 7 or Eq. 12).
One update's change is the mean over θ's components (every output's lengthscales, signal and noise variance) of
``|log θ_e - log θ_{e-1}|`` between the θ that consecutive episodes' policy searches used (``metrics.csv``'s
``theta/`` columns); Table S4 averages it over a run's first :data:`EARLY_UPDATES` updates, Table S5 over the rest.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from qtl.recorder import METRICS_FILE, THETA_PREFIX
from qtl.report.discover import Experiment
from qtl.report.stats import CELL_KEYS, VALUE, cells_json, over_seeds
from qtl.report.tables import approach_grid, stat_text

EARLY_UPDATES = 5  # "the first iterations of the learning process" (Section 5.1)
CHANGE_DIGITS = 3
THETA_COLUMN = f"{THETA_PREFIX}/"
STABILITY_TITLES: dict[str, str] = {
    "early": (
        f"**Table S4.** Hyper-parameter change in the first {EARLY_UPDATES} model updates: the mean over θ's "
        "components of |Δ log θ| between consecutive episodes' models (θ as the policy search used it), averaged "
        "over those updates; mean ± std over seeds."
    ),
    "late": (
        f"**Table S5.** Hyper-parameter change after the first {EARLY_UPDATES} model updates, the same measure "
        "as Table S4 averaged over every later update; mean ± std over seeds."
    ),
}


def theta_path(run_dir: Path, episodes: int) -> np.ndarray:
    """The θ of each of the run's first ``episodes`` episodes that had a model: `(E, P)` (P = 0: none logged)."""
    frame = pd.read_csv(run_dir / METRICS_FILE, nrows=episodes, usecols=lambda c: c.startswith(THETA_COLUMN))
    values = frame.to_numpy(dtype=float)
    if values.shape[1] == 0:
        return values
    return values[np.isfinite(values).all(axis=1)]


def theta_changes(thetas: np.ndarray) -> np.ndarray:
    """Change per update: the mean over components of ``|Δ log θ|`` between consecutive rows of `(E, P)` θ: `(E-1,)`."""
    if thetas.shape[0] < 2 or thetas.shape[1] == 0:
        return np.zeros(0)
    if np.any(thetas <= 0):
        raise ValueError("θ holds a non-positive value: lengthscales and variances are positive, so the metrics "
                         "file is not a qtl run's")
    return np.abs(np.diff(np.log(thetas), axis=0)).mean(axis=1)


def stability_values(experiment: Experiment, early: int = EARLY_UPDATES) -> pd.DataFrame:
    """Mean change of the first ``early`` updates (``early``) and of the later ones (``late``) per run:
    ``metric, approach, label, seed, value``; runs without θ columns, or without updates in a part, are left out."""
    rows = []
    for approach, by_label in experiment.cells.items():
        for label, cell in by_label.items():
            for seed in cell.seeds:
                changes = theta_changes(theta_path(cell.run_dirs[seed], cell.episodes))
                for metric, part in (("early", changes[:early]), ("late", changes[early:])):
                    if part.size:
                        rows.append((metric, approach, label, seed, float(part.mean())))
    return pd.DataFrame(rows, columns=["metric", *CELL_KEYS, "seed", VALUE])


def stability_markdown(experiment: Experiment) -> list[str]:
    """Tables S4-S5 (rows approaches, columns labels, seeds per row); empty where no run logged θ."""
    values = stability_values(experiment)
    tables = []
    for metric, title in STABILITY_TITLES.items():
        of_metric = values[values["metric"] == metric]
        if of_metric.empty:
            continue
        stats = over_seeds(of_metric, CELL_KEYS)
        text = pd.Series([stat_text(m, s, CHANGE_DIGITS) for m, s in zip(stats["mean"], stats["std"], strict=True)],
                         index=stats.index)
        tables.append(title + "\n\n" + approach_grid(text, stats["n"], experiment.approaches, experiment.labels))
    return tables


def stability_json(experiment: Experiment) -> dict[str, object] | None:
    """Tables S4-S5 for ``tables.json``: ``early_updates`` and, per part, approach -> label -> mean, std, n and
    per-seed values; None where no run logged θ."""
    values = stability_values(experiment)
    if values.empty:
        return None
    out: dict[str, object] = {"early_updates": EARLY_UPDATES}
    for metric in STABILITY_TITLES:
        of_metric = values[values["metric"] == metric]
        out[metric] = cells_json(of_metric) if not of_metric.empty else {}
    return out

