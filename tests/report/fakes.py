"""Synthetic experiment directories with hand-computed numbers, as ``qtl-train`` sweeps leave them."""

from __future__ import annotations

import math
import re
from pathlib import Path

import yaml

from qtl.recorder import METRICS_FILE

NAN = math.nan

# approach -> label -> seed -> (returns, compliance per episode); success is return >= 30.
# Hand-computed numbers (final = mean of the last 3, AUC = trapezoid, TTC = first episode >= 0.95 final):
CARTPOLE = {
    "qtl_bayesian": {
        "m1.5": {
            0: ([20, 30, 40, 40, 40, 40], [NAN, 0.5, 0.5, 0.5, 0.5, 0.6]),  # final 40, AUC 180, TTC 2
            1: ([20, 40, 40, 40, 40, 40], [NAN, 0.7, 0.7, 0.7, 0.7, 0.8]),  # final 40, AUC 190, TTC 1
        },
        "m2.0": {  # no compliance: Table 4 falls back to PILCO's runs
            0: ([10, 20, 20, 20, 20, 20], [NAN] * 6),  # final 20, AUC 95, TTC 1
            1: ([10, 10, 30, 30, 30, 30], [NAN] * 6),  # final 30, AUC 120, TTC 2
        },
    },
    "pilco": {
        "m2.0": {
            0: ([0, 0, 10, 20, 20, 20], [NAN, 0.2, 0.2, 0.2, 0.2, 0.25]),  # final 20, AUC 60, TTC 3
            # 8 episodes, cut to the cell's common 6: final 14, AUC 54, TTC 4 (uncut: final 72);
            # no compliance at episode 5 (0.9 at the cut-off episode 7 must not count).
            1: ([0, 10, 10, 10, 16, 16, 100, 100], [NAN, 0.3, 0.3, 0.3, 0.3, NAN, 0.9, 0.9]),
        },
        "m1.5": {
            0: ([0, 10, 20, 30, 30, 30], [NAN, 0.1, 0.1, 0.1, 0.1, 0.1]),  # final 30, AUC 105, TTC 3
            1: ([0, 36, 20, 36, 36, 36], [NAN, 0.1, 0.1, 0.1, 0.1, 0.1]),  # final 36, AUC 146, TTC 1
        },
    },
}
HELICOPTER_ENV = {"id": "qtl/Helicopter-v0", "mass": 6.0, "horizon": 200}  # as a run's .hydra/config.yaml has it


def write_run(run_dir: Path, returns: list[float], compliance: list[float] | None = None,
              overrides: list[str] | None = None, env: dict | None = None, horizon: int | None = None,
              extra: dict[str, list[float]] | None = None) -> None:
    """A run directory as ``qtl-train`` leaves it: ``metrics.csv`` (with the ``extra`` columns, one value per
    episode, NaN written empty), ``.hydra/overrides.yaml`` (and ``config.yaml`` with ``task.env`` and
    ``task.horizon`` when ``env`` is given)."""
    compliance = compliance or [NAN] * len(returns)
    extra = extra or {}
    (run_dir / ".hydra").mkdir(parents=True)
    rows = [",".join(["episode,kind,return,predicted_return,success,compliance", *extra])]
    for episode, (ret, comp) in enumerate(zip(returns, compliance, strict=True)):
        kind = "random" if episode == 0 else "policy"
        cells = ["" if math.isnan(values[episode]) else repr(values[episode]) for values in extra.values()]
        rows.append(",".join([f"{episode},{kind},{ret},nan,{int(ret >= 30)},{'' if math.isnan(comp) else comp}",
                              *cells]))
    (run_dir / METRICS_FILE).write_text("\n".join(rows) + "\n")
    (run_dir / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides or []))
    if env is not None:
        task = {"env": env} if horizon is None else {"env": env, "horizon": horizon}
        (run_dir / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"seed": 0, "task": task}))


def make_experiment(root: Path, runs: dict, sources: int = 2) -> Path:
    """``root`` with ``sources`` source runs and the target runs of ``runs`` (as :data:`CARTPOLE`)."""
    for seed in range(sources):
        write_run(root / "source" / f"seed_{seed}", [0.0, 5.0, 9.0, 10.0], overrides=[f"seed={seed}"])
    for approach, by_label in runs.items():
        for label, by_seed in by_label.items():
            for seed, (returns, compliance) in by_seed.items():
                overrides = [f"seed={seed}", f"approach={approach}", f"task.env.pole_mass={label[1:]}"]
                write_run(root / "target" / approach / label / f"seed_{seed}", returns, compliance, overrides)
    return root


def make_helicopter(root: Path, record: dict | None = None) -> Path:
    """A one-label helicopter experiment, one seed per approach; ``record`` is written as ``experiment.yaml``."""
    overrides = ["approach=pilco", "seed=0"]
    write_run(root / "target" / "pilco" / "helicopter" / "seed_0", [0, 50, 100, 130, 130, 130],
              overrides=overrides, env=HELICOPTER_ENV)  # final 130, AUC 475, TTC 3
    write_run(root / "target" / "qtl_bayesian" / "helicopter" / "seed_0", [50, 120, 131, 132, 133, 131],
              overrides=overrides)  # final 132, AUC 606.5, TTC 2
    if record is not None:
        (root / "experiment.yaml").write_text(yaml.safe_dump(record))
    return root


def table_rows(markdown: str) -> list[tuple[str, ...]]:
    """The cells of every markdown table row in ``markdown`` (header rows included, alignment rows left out)."""
    rows = []
    for line in markdown.splitlines():
        if not line.startswith("|"):
            continue
        cells = tuple(cell.strip() for cell in line.strip().strip("|").split("|"))
        if not all(re.fullmatch(r":?-+:?", cell) for cell in cells):
            rows.append(cells)
    return rows
