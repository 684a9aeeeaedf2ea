"""qtl-compliance: task compliance (Eq. 14) of finished target runs against a source run, at one or more resolutions.

Each run's GP is rebuilt from its last checkpoint (its data and stored θ, no fitting): the source's as
transfer reads it, each target's as its last model. Printed as a markdown table (one row per target run,
one column per resolution ρ; ``transfer.compliance_resolution``), and as JSON with ``--json PATH``, the runs
named relative to the repository.
``--compliance`` chooses the estimate as ``transfer.compliance`` does (default: kernel, with
``--bandwidth scott``); ``--temperature`` is the likelihood ratio's κ.

    qtl-compliance SOURCE_RUN TARGET_RUN [TARGET_RUN ...] [--resolution 0 0.1]
        [--compliance kernel|likelihood_ratio] [--bandwidth scott|none] [--temperature KAPPA] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path

import torch

from qtl.errors import UserError
from qtl.features import AngleFeatures
from qtl.report.paths import recorded_path
from qtl.report.tables import markdown_table
from qtl.transfer.compliance import BANDWIDTHS, COMPLIANCES, DEFAULT_COMPLIANCE, compliance_value
from qtl.transfer.source import SourceRun

PROG = "qtl-compliance"


def parser() -> argparse.ArgumentParser:
    """The command line of ``qtl-compliance``."""
    found = argparse.ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    found.add_argument("source", type=Path, help="the source run's directory")
    found.add_argument("targets", type=Path, nargs="+", help="finished target runs' directories")
    found.add_argument("--resolution", type=float, nargs="+", default=[0.0], help="resolutions ρ (default 0)")
    found.add_argument("--compliance", choices=sorted(COMPLIANCES), default=DEFAULT_COMPLIANCE)
    found.add_argument("--bandwidth", choices=BANDWIDTHS, default="scott", help="the kernel estimate's bandwidth")
    found.add_argument("--temperature", type=float, help="κ of the likelihood ratio (default: the state dimension)")
    found.add_argument("--json", type=Path, help="also write the results here")
    return found


def compliance_rows(source: SourceRun, targets: Sequence[Path], args: argparse.Namespace) -> list[dict]:
    """Per target run: its name, last episode, tuples and Λ at each resolution against ``source``."""
    features = AngleFeatures(source.task.state_dim, source.task.angle_dims)
    source_model = source.model(features)
    rows = []
    for path in targets:
        target = SourceRun.load(path)
        source.check_compatible(target.task, target.outputs)
        model = target.model(features)
        values = {rho: compliance_value(args.compliance, source_model, model, bandwidth=args.bandwidth,
                                        temperature=args.temperature, resolution=rho)
                  for rho in args.resolution}
        rows.append({"target": recorded_path(path), "episode": target.episode, "n": len(target.dataset),
                     "compliance": {str(rho): value for rho, value in values.items()}})
    return rows


def main(argv: Sequence[str] | None = None) -> None:
    """Parse the arguments, rebuild the runs' GPs, print Λ per target and resolution (and write JSON)."""
    cli = parser()
    args = cli.parse_args(argv)
    if args.temperature is not None and args.compliance != "likelihood_ratio":
        cli.error("--temperature tempers the likelihood ratio only: add --compliance likelihood_ratio")
    if missing := [path for path in (args.source, *args.targets) if not path.is_dir()]:
        cli.error(f"{missing[0]} is not a directory: give finished runs' directories")
    torch.set_num_threads(1)
    try:
        source = SourceRun.load(args.source)
        rows = compliance_rows(source, args.targets, args)
    except UserError as err:  # not a run, no checkpoint, another task: one line
        cli.error(str(err).splitlines()[0])
    how = args.compliance + (f", bandwidth {args.bandwidth}" if args.compliance == "kernel" else "")
    print(f"source: {recorded_path(args.source)} (episode {source.episode}, n = {len(source.dataset)}); "
          f"compliance: {how}\n")
    print(markdown_table([[row["target"], row["n"], *(f"{v:.2f}" for v in row["compliance"].values())] for row in rows],
                         ["target run", "n", *(f"Λ, ρ = {rho:g}" for rho in args.resolution)],
                         "lr" + "r" * len(args.resolution)))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"source": recorded_path(args.source), "compliance": args.compliance,
                                         "bandwidth": args.bandwidth, "targets": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
