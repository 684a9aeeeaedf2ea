"""The paper's tables and figures (Section 5: Tables 1-6, Figs. 1-3) from an experiment directory.

Reads ``<root>/source/seed_<k>/`` and ``<root>/target/<approach>/<label>/seed_<k>/`` (and
``<root>/experiment.yaml`` when present) and writes ``report.md``, ``tables.json`` and
``fig_learning_curves.png/.pdf`` into ``--out`` (default ``<root>/report``); see :mod:`qtl.report`.
The helicopter's autopilot line is read from ``experiment.yaml``, where ``scripts/run_experiment.py``
records it; ``--record-reference`` flies the autopilot and records it first (for runs made another way).

    python scripts/report.py runs/cartpole
    python scripts/report.py runs/cartpole --finished-only   # mid-sweep: the finished runs only
    python scripts/report.py runs/aircraft --out docs/aircraft
    python scripts/report.py runs/aircraft --record-reference
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from qtl.report import record_reference, write_report


def main() -> None:
    """Parse the arguments, record the reference line if asked, write the report, print its path."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="the experiment directory")
    parser.add_argument("--out", type=Path, default=None, help="where the report goes (default: <root>/report)")
    parser.add_argument("--record-reference", action="store_true",
                        help="fly the helicopter's autopilot and record its return in <root>/experiment.yaml first")
    parser.add_argument("--finished-only", action="store_true",
                        help="leave out (and name) the runs with fewer episodes than configured: a sweep still running")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    if args.record_reference and record_reference(args.root) is None:
        logging.getLogger(__name__).warning("%s does not fly the helicopter: no reference line recorded", args.root)
    try:
        print(write_report(args.root, args.out, finished_only=args.finished_only))
    except ValueError as err:  # what the experiment directory lacks or holds wrong, in one line
        parser.exit(1, f"{parser.prog}: {err}\n")


if __name__ == "__main__":
    main()
