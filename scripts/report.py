"""The paper's tables and figures (Section 5: Tables 1-6, Figs. 1-3) from an experiment directory.

Reads ``<root>/source/seed_<k>/`` and ``<root>/target/<approach>/<label>/seed_<k>/`` (and
``<root>/experiment.yaml`` when present) and writes ``report.md``, ``tables.json`` and
``fig_learning_curves.png/.pdf`` into ``--out`` (default ``<root>/report``); see :mod:`qtl.report`.

    python scripts/report.py runs/cartpole
    python scripts/report.py runs/aircraft --out docs/aircraft
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from qtl.report import write_report


def main() -> None:
    """Parse the arguments, write the report, print its path."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("root", type=Path, help="the experiment directory")
    parser.add_argument("--out", type=Path, default=None, help="where the report goes (default: <root>/report)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    print(write_report(args.root, args.out))


if __name__ == "__main__":
    main()
