"""qtl-report: the paper's tables and figures (Section 5: Tables 1-6, Figs. 1-3) from an experiment directory.

Reads ``<root>/source/seed_<k>/`` and ``<root>/target/<approach>/<label>/seed_<k>/`` (and
``<root>/experiment.yaml`` when present) and writes ``report.md``, ``tables.json`` and
``fig_learning_curves.png/.pdf`` into ``--out`` (default ``<root>/report``); see :mod:`qtl.report`.
The helicopter's autopilot line is read from ``experiment.yaml``, where ``qtl-experiment``
records it; ``--record-reference`` flies the autopilot and records it first (for runs made another way).
``--export DIR`` writes no report: it copies the small files the report is rebuilt from (configs, CSVs,
``experiment.yaml``, ``final_policies.json``, the report) into a new folder, without checkpoints, events or logs
(:mod:`qtl.report.export`).

    qtl-report runs/cartpole                   # or: python -m qtl.report.cli runs/cartpole
    qtl-report runs/cartpole --finished-only   # mid-sweep: the finished runs only
    qtl-report runs/aircraft --out docs/aircraft
    qtl-report runs/aircraft --record-reference
    qtl-report runs/cartpole --export docs/experiments/cartpole
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence
from pathlib import Path

from qtl.report.autopilot import record_reference
from qtl.report.export import export
from qtl.report.write import write_report


def parser() -> argparse.ArgumentParser:
    """The command line of ``qtl-report`` (and ``python -m qtl.report.cli``)."""
    found = argparse.ArgumentParser(prog="qtl-report", description=__doc__.splitlines()[0])
    found.add_argument("root", type=Path, help="the experiment directory")
    found.add_argument("--out", type=Path, default=None, help="where the report goes (default: <root>/report)")
    found.add_argument("--record-reference", action="store_true",
                       help="fly the helicopter's autopilot and record its return in <root>/experiment.yaml first")
    found.add_argument("--finished-only", action="store_true",
                       help="leave out (and name) the runs with fewer episodes than configured: a sweep still running")
    found.add_argument("--export", type=Path, default=None, metavar="DIR",
                       help="write no report: copy the files the report is rebuilt from into DIR, a new or empty "
                            "folder (no checkpoints, events or logs); refused if a run is unfinished, unless "
                            "--finished-only")
    return found


def main(argv: Sequence[str] | None = None) -> None:
    """Parse the arguments; export, or record the reference line if asked and write the report; print the path."""
    cli = parser()
    args = cli.parse_args(argv)
    if args.export is not None and (args.out is not None or args.record_reference):
        cli.error("--export copies the experiment as it is: it takes neither --out nor --record-reference")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        if args.export is not None:
            written = export(args.root, args.export, finished_only=args.finished_only)
            print(f"{args.export} ({len(written)} files)")
            return
        if args.record_reference and record_reference(args.root) is None:
            logging.getLogger(__name__).warning("%s does not fly the helicopter: no reference line recorded",
                                                args.root)
        print(write_report(args.root, args.out, finished_only=args.finished_only))
    except ValueError as err:  # what the experiment directory (or the export's folder) lacks or holds wrong, one line
        cli.exit(1, f"{cli.prog}: {err}\n")


if __name__ == "__main__":
    main()
