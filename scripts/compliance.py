"""Task compliance (Eq. 14) of finished target runs against a source run, at one or more resolutions.

Each run's GP is rebuilt from its last checkpoint (its data and stored θ, no fitting): the source's as
transfer reads it, each target's as its last model. Printed as a markdown table (one row per target run,
one column per resolution ρ; ``transfer.compliance_resolution``), and as JSON with ``--json PATH``, the runs
named relative to the repository.
``--compliance`` chooses the estimate as ``transfer.compliance`` does (default: kernel, with
``--bandwidth scott``); ``--temperature`` is the likelihood ratio's κ.

    .venv/bin/python scripts/compliance.py SOURCE_RUN TARGET_RUN [TARGET_RUN ...] [--resolution 0 0.1]
        [--compliance kernel|likelihood_ratio] [--bandwidth scott|none] [--temperature KAPPA] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from qtl.features import AngleFeatures
from qtl.report.paths import recorded_path
from qtl.transfer.compliance import BANDWIDTHS, COMPLIANCES, DEFAULT_COMPLIANCE, compliance_value
from qtl.transfer.source import SourceRun


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path)
    parser.add_argument("targets", type=Path, nargs="+")
    parser.add_argument("--resolution", type=float, nargs="+", default=[0.0])
    parser.add_argument("--compliance", choices=sorted(COMPLIANCES), default=DEFAULT_COMPLIANCE)
    parser.add_argument("--bandwidth", choices=BANDWIDTHS, default="scott", help="the kernel estimate's bandwidth")
    parser.add_argument("--temperature", type=float, help="κ of the likelihood ratio (default: the state dimension)")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()
    if args.temperature is not None and args.compliance != "likelihood_ratio":
        parser.error("--temperature tempers the likelihood ratio only: add --compliance likelihood_ratio")
    torch.set_num_threads(1)

    source = SourceRun.load(args.source)
    features = AngleFeatures(source.task.state_dim, source.task.angle_dims)
    source_model = source.model(features)
    rows = []
    for path in args.targets:
        target = SourceRun.load(path)
        source.check_compatible(target.task)
        model = target.model(features)
        values = {rho: compliance_value(args.compliance, source_model, model, bandwidth=args.bandwidth,
                                        temperature=args.temperature, resolution=rho)
                  for rho in args.resolution}
        rows.append({"target": recorded_path(path), "episode": target.episode, "n": len(target.dataset),
                     "compliance": {str(rho): value for rho, value in values.items()}})
    how = args.compliance + (f", bandwidth {args.bandwidth}" if args.compliance == "kernel" else "")
    print(f"source: {recorded_path(args.source)} (episode {source.episode}, n = {len(source.dataset)}); "
          f"compliance: {how}\n")
    print("| target run | n | " + " | ".join(f"Λ, ρ = {rho:g}" for rho in args.resolution) + " |")
    print("| --- | ---: | " + " | ".join("---:" for _ in args.resolution) + " |")
    for row in rows:
        print(f"| {row['target']} | {row['n']} | " + " | ".join(f"{v:.2f}" for v in row["compliance"].values()) + " |")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"source": recorded_path(args.source), "compliance": args.compliance,
                                         "bandwidth": args.bandwidth, "targets": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
