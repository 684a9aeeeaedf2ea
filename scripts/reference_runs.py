"""Small reference runs of the CLI whose ``metrics.csv`` a refactor must reproduce byte for byte.

Each reference is one ``qtl-train`` run at a small budget on one torch thread (same seed, same kernels, same
threads: the conditions under which a run is reproducible). ``record`` makes them under ``DIR`` (a source run
first, for the transfer reference); ``compare`` reruns them under ``DIR2`` and says, per run, whether its
``metrics.csv`` equals the recorded one byte for byte, or else whether every column the recorded file has is
byte-identical in the new one (columns added since, e.g. a new metric, are named). Exit status 1 when any recorded
column differs.

    python scripts/reference_runs.py record runs/reference/before
    python scripts/reference_runs.py compare runs/reference/before runs/reference/after
"""

from __future__ import annotations

import argparse
import csv
import filecmp
import subprocess
import sys
from pathlib import Path

BUDGET = ["episodes=2", "task.horizon=15", "task.success.last_steps=3", "task.policy_size=10", "model.restarts=2",
          "model.max_iter=15", "threads=1", "seed=3", "progress=false"]
LBFGS = ["optimizer.max_iter=8", "optimizer.restarts=2"]
# name -> overrides; "{source}" is the source run of the transfer reference.
REFERENCES: dict[str, list[str]] = {
    "source": [*LBFGS],
    "moment_matching": [*LBFGS, "task.env.pole_mass=1.0"],
    "reference_path": [*LBFGS, "task.env.pole_mass=1.0", "kernels.backend=torch", "kernels.moments=reference",
                       "optimizer.batched=false", "model.warm_start=false"],
    "particles_mc_pilco": ["task=cartpole_dt005", "recipe=mc_pilco", "task.horizon=20", "optimizer.steps=5",
                           "optimizer.plateau.min_steps=2", "propagation.num_particles=30"],
    "transfer_bayesian": [*LBFGS, "task.env.pole_mass=2.0", "transfer.source={source}", "approach=qtl_bayesian"],
    "sparse": [*LBFGS, "task.env.pole_mass=1.0", "model=sparse", "model.inducing=10"],
}


def run_all(root: Path) -> None:
    """Make every reference run under ``root`` (runs already there are left as they are)."""
    for name, overrides in REFERENCES.items():
        out = root / name
        if (out / "metrics.csv").is_file():
            continue
        filled = [o.replace("{source}", str(root / "source")) for o in overrides]
        subprocess.run([sys.executable, "-m", "qtl", *BUDGET, *filled, f"hydra.run.dir={out}"], check=True)


def main() -> None:
    """Record the references, or rerun and compare them."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("action", choices=["record", "compare"])
    parser.add_argument("dirs", type=Path, nargs="+", help="record: DIR; compare: DIR (recorded) DIR2 (new)")
    args = parser.parse_args()
    if (args.action == "record") != (len(args.dirs) == 1) or len(args.dirs) > 2:
        parser.error("record takes one directory, compare two")
    run_all(args.dirs[-1])
    if args.action == "compare":
        before, after = args.dirs
        verdicts = {name: compare(before / name / "metrics.csv", after / name / "metrics.csv") for name in REFERENCES}
        for name, verdict in verdicts.items():
            print(f"{name}: {verdict}")
        sys.exit(1 if any(v.startswith("DIFFERS") for v in verdicts.values()) else 0)


def compare(recorded: Path, new: Path) -> str:
    """Whether ``new`` equals ``recorded`` byte for byte, or keeps each of its columns byte for byte (and adds some)."""
    if filecmp.cmp(recorded, new, shallow=False):
        return "byte-identical metrics.csv"
    with open(recorded, newline="") as f:
        old_rows = list(csv.DictReader(f))
    with open(new, newline="") as f:
        new_rows = list(csv.DictReader(f))
    old_columns, new_columns = list(old_rows[0]) if old_rows else [], list(new_rows[0]) if new_rows else []
    missing = [c for c in old_columns if c not in new_columns]
    kept = [c for c in old_columns if c not in missing]
    changed = sorted({c for a, b in zip(old_rows, new_rows, strict=False) for c in kept if a[c] != b[c]})
    if missing or changed or len(old_rows) != len(new_rows):
        return (f"DIFFERS metrics.csv (rows {len(old_rows)} vs {len(new_rows)}; changed columns {changed}; "
                f"missing columns {missing})")
    added = [c for c in new_columns if c not in old_columns]
    return f"every recorded column byte-identical; columns added: {', '.join(added)}"


if __name__ == "__main__":
    main()
