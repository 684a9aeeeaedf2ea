"""Research — who should judge source samples: the relevance w of a source's tuples under successive judging θ.

Takes a target run's first ``--episodes`` episodes as the target's tuples and a source run's tuples (thinned as
``transfer.samples=relevance`` thins them), and prints the mean w per modelled output judged by:

- θ_s, the source's θ (what the first model of a sample-transfer run starts from);
- the last model, ``--refits`` times over: the GP fitted on the target's tuples plus the source's with the last w,
  whose θ then judges them again (how relevance was computed before the judge);
- the judge: θ fitted on the target's tuples alone, from θ_s (what ``transfer.samples=relevance`` does).

The docs' figure (mountain car 100 % → 300 %, velocity w 0.17 → 0.95 by the last model, 0.31 by the judge) is

    python scripts/research/relevance_drift.py runs/bench_kinematic/mountaincar-delta/seed_0 \
        runs/bench_samples/mountaincar-3.0/pilco/seed_0 --episodes 1

The last line of the output is the same as JSON.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from qtl.bench import markdown_table
from qtl.bench.refit import loaded
from qtl.data import TransitionDataset
from qtl.models import GPHyperparameters
from qtl.transfer import SourceRun
from qtl.transfer.samples import SourceSamples, WeightedSamples


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path, help="the source run")
    parser.add_argument("target", type=Path, help="a run of the target task (its first episodes are the target's)")
    parser.add_argument("--episodes", type=int, default=1, help="the target's episodes to use (from its first)")
    parser.add_argument("--refits", type=int, default=3, help="refits judged by the last model")
    parser.add_argument("--max-samples", type=int, default=200, help="transfer.max_source_samples")
    parser.add_argument("--seed", type=int, default=0, help="the fits' random stream")
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.refits < 1 or args.max_samples < 1:
        parser.error("--episodes, --refits and --max-samples must be >= 1")

    run = loaded(args.target, None, [])
    parts = run.parts
    source = SourceRun.load(args.source)
    stored = run.checkpoint["dataset"]
    if args.episodes > len(stored["states"]):
        parser.error(f"--episodes {args.episodes}: the target run holds {len(stored['states'])} episodes")
    data = TransitionDataset(parts.task.state_dim, parts.task.action_dim, parts.task.angle_dims)
    for states, actions in zip(stored["states"][:args.episodes], stored["actions"][:args.episodes], strict=True):
        data.add_episode(states, actions)
    x, y = parts.gp_data(data)
    tuples = SourceSamples.of(source.dataset, parts.features, parts.modelled, args.max_samples, parts.dtype)
    theta_s = source.theta.to(dtype=parts.dtype)

    rows: list[dict] = []

    def judged(by: str, theta: GPHyperparameters, outputs: tuple[int, ...]) -> WeightedSamples:
        weighted = tuples.weighted(x, y, theta, outputs)
        rows.append({"judged by": by, **{f"w, output {d}": round(float(weighted.weights[:, k].mean()), 3)
                                         for k, d in enumerate(tuples.outputs)}})
        return weighted

    weighted = judged("θ_s", theta_s, tuple(source.theta_outputs))
    for refit in range(1, args.refits + 1):
        model = parts.fit_dynamics(data, torch.Generator().manual_seed(args.seed), start=theta_s, samples=weighted)
        weighted = judged(f"the last model, refit {refit}", model.hyperparameters, tuple(model.outputs))
    own = parts.fit_own(data, torch.Generator().manual_seed(args.seed), theta_s)
    judged("the judge: the target's tuples alone", own.hyperparameters, tuple(own.outputs))

    print(f"{len(x)} target tuples ({args.episodes} episode(s)), {len(tuples.inputs)} source tuples")
    print(markdown_table([list(r.values()) for r in rows], list(rows[0])))
    report = {"target_tuples": len(x), "source_tuples": len(tuples.inputs), "rows": rows}
    print(json.dumps(report))
    return report


if __name__ == "__main__":
    main()
