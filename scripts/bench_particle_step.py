"""Benchmark one particle rollout + gradient of a finished run's recipe: the RBF network's three forward forms.

    .venv/bin/python scripts/bench_particle_step.py RUN_DIR [--checkpoint PATH] [--repeats 7] [--threads 1]
        [--output docs/bench/particle_step.json] [--no-docs]

On the run's data (its latest checkpoint, or ``--checkpoint``), the model refitted with the run's settings
and the run's policy with the recipe's starting dropout (``optimizer.dropout``), one search evaluation, a
rollout of the task's horizon and its ∂V/∂ψ, is timed with ``RBFNetwork.forward`` by the plain autograd
form (the old path), by the fused torch op and by its compiled twin (``qtl.kernels.Engine.network``;
the native one needs the build and ``kernels.moments=native``, else it is skipped), in alternation in this one
process, after one warm-up each. Ratios of the medians against the plain form are the speed-ups; the forms'
values of each round (the same dropout masks, particle noise and drawn functions) are checked equal first.
Writes JSON and the "particle_step" section of ``docs/benchmarks.md``.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from qtl.bench import (
    ROOT,
    command_line,
    commit,
    display_path,
    machine,
    markdown_table,
    today,
    write_results,
    write_section,
)
from qtl.bench.refit import loaded, refitted
from qtl.checkpoint import latest_checkpoint
from qtl.seeding import torch_generator

# The network's forms, by ``Engine.network``: the plain autograd form (the old path), the fused op, its compiled twin.
FORMS = {"reference": "reference", "fused": "fused", "native": "auto"}
# The two forms' values of one evaluation agree to this (relative): they differ in the order of operations,
# which a 100-step closed loop amplifies, but not beyond this over one rollout.
VALUE_RTOL = 1e-6


def main() -> None:
    """Time each form in alternation on the run's data; check their values agree; write the JSON and the section."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--checkpoint", type=Path, help="default: the run's latest")
    parser.add_argument("--repeats", type=int, default=7, help="timed evaluations per form, alternating")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "bench" / "particle_step.json")
    parser.add_argument("--no-docs", action="store_true", help="do not write the section of docs/benchmarks.md")
    args = parser.parse_args()
    if not args.run_dir.is_dir():
        parser.error(f"{args.run_dir} is not a run directory")
    if args.repeats < 1:
        parser.error("--repeats must be at least 1")
    torch.set_num_threads(args.threads)

    checkpoint_path = args.checkpoint or latest_checkpoint(args.run_dir)
    run = loaded(args.run_dir, checkpoint_path, [])
    cfg = run.config
    particle_run = cfg.propagation["_target_"].endswith("Particles")
    if not particle_run or not cfg.policy["_target_"].endswith("rbf_network_policy"):
        parser.error(f"{args.run_dir} is not a particle run with policy=rbf_network (e.g. recipe=mc_pilco)")
    data, model = refitted(run)
    parts, policy = run.parts, run.policy()
    forms = [form for form in FORMS if form != "native" or parts.engine.moments == "native"]
    propagators = {form: parts.make_propagator(model, policy, parts.reward, angle_dims=parts.task.angle_dims,
                                               engine=parts.engine.replace(network=FORMS[form])) for form in forms}

    def evaluate(form: str, seed: int) -> tuple[float, float]:
        """One evaluation (value and ∂V/∂ψ) under ``form``, with dropout masks from ``seed``: (value, seconds)."""
        propagator = propagators[form]
        policy.set_dropout(cfg.optimizer.dropout, torch_generator(seed, 0, 0))
        propagator.calls = seed  # the evaluation number, which picks the draw of particle noise and functions
        policy.zero_grad()
        tic = time.perf_counter()
        value = propagator.expected_return(parts.start, parts.task.horizon)
        value.backward()
        return value.item(), time.perf_counter() - tic

    times: dict[str, list[float]] = {form: [] for form in forms}
    values: dict[str, list[float]] = {form: [] for form in forms}
    for repeat in range(args.repeats + 1):  # the first round is the warm-up
        for form in forms:
            value, seconds = evaluate(form, repeat)
            if repeat:
                times[form].append(seconds)
                values[form].append(value)
    spread = max(abs(a - b) / max(abs(b), 1e-12)
                 for form in forms for a, b in zip(values[form], values["reference"], strict=True))
    medians = {form: statistics.median(ts) for form, ts in times.items()}
    result = {
        "run": display_path(args.run_dir.resolve()),
        "checkpoint": display_path(Path(checkpoint_path).resolve()),
        "n": len(data),
        "particles": cfg.propagation.num_particles,
        "horizon": parts.task.horizon,
        "num_basis": cfg.policy.num_basis,
        "dropout": cfg.optimizer.dropout,
        "formulation": parts.engine.moments,
        "times_s": times,
        "median_s": medians,
        "ratios": {form: medians[form] / medians["reference"] for form in forms},
        "max_value_relative_difference": spread,
    }
    info = {"command": command_line(), "date": today(), "commit": commit(),
            "machine": machine()}
    write_results(args.output, info, [result])
    print(f"n = {result['n']}: " + ", ".join(f"{form} {medians[form]:.3f} s ({result['ratios'][form]:.2f}×)"
                                             for form in forms) + f"; values agree to {spread:.1e}")
    if spread > VALUE_RTOL:
        raise SystemExit(f"the two forms' values differ by {spread:.2e} (relative), beyond {VALUE_RTOL:g}")
    if not args.no_docs:
        write_section("particle_step", markdown(result, info, args.output))


def markdown(result: dict, info: dict, output: Path) -> str:
    """The section of docs/benchmarks.md: each form's median and its ratio to the plain form."""
    measured_on, medians, ratios = info["machine"], result["median_s"], result["ratios"]
    names = {"reference": "plain autograd form (old path)", "fused": "fused torch op", "native": "compiled op"}
    return "\n".join([
        "## Particle rollout + gradient: the RBF network's forward forms",
        "",
        f"`{info['command']}` at {info['commit']}, {info['date']}, {measured_on['cpu']}, "
        f"{measured_on['torch_threads']} torch thread(s); JSON `{display_path(output)}`. One search evaluation "
        f"(a {result['horizon']}-step rollout of P = {result['particles']} particles and its ∂V/∂ψ) on "
        f"`{result['checkpoint']}`'s data (n = {result['n']}), its policy ({result['num_basis']} bases) with dropout "
        f"{result['dropout']}, the forms alternating in one process ({len(result['times_s']['reference'])} timed "
        f"evaluations each, after one warm-up); `kernels.moments={result['formulation']}`. The forms' values "
        f"agree to {result['max_value_relative_difference']:.1e} (relative).",
        "",
        markdown_table([[names[form], f"{medians[form]:.3f}", f"{ratios[form]:.2f}×"] for form in medians],
                       ["form of `RBFNetwork.forward`", "median s per evaluation", "ratio to the old path"], "lrr"),
    ])


if __name__ == "__main__":
    main()
