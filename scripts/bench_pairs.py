"""Benchmark the a = b pairs' exp sums from their lower triangles against every pair's full sum, in one run.

For each full-scale preset's task: the model the sweep fits just past ``model.sparse_above`` (the sparse
GP, m = 300, as `bench_scale.py`), then one policy-search round (rollout + gradient of the optimizer's R
restarts at once) timed alternately with the compiled moments' lower pair sums (the default) and with
every pair's full n x n sum (``Engine.lower_pairs=False``), and the values and gradients
of both compared. Of the E(E+1)/2 output pairs, E are a = b pairs whose S_aa is symmetric, so the lower
sums skip about E/2 of the pair sums' entries: ≤ 20 % for the cart-pole (E = 4), ≤ 33 % for the
mountain car (E = 2), ≤ 8 % for the aircraft (E = 12). Writes ``docs/bench/pairs.json`` and its section
of ``docs/benchmarks.md``.

    .venv/bin/python scripts/bench_pairs.py [--experiments cartpole mountaincar] [--repeats 7] [--threads 1]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

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
from qtl.bench.scale import compose_stage, stage_model
from qtl.bench.search import SEARCH_EPISODE, batched_round
from qtl.policies import batched_policy, psi_names, set_psi, stack_psi
from qtl.seeding import SEARCH_STREAM, torch_generator

PRESETS = {"cartpole": "cartpole_source", "mountaincar": "mountaincar_source", "aircraft": "aircraft_source"}
DEFAULT_OUTPUT = ROOT / "docs" / "bench" / "pairs.json"
SECTION = "bench_pairs"


def round_outputs(parts: Any, model: Any, policy: Any, seed: int) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """V of the R restarts and ∂ΣV/∂ψ of one round (the starting points of ``batched_round``)."""
    states = parts.search.starting_states(policy, torch_generator(seed, SEARCH_EPISODE, SEARCH_STREAM))
    batched = batched_policy(policy, len(states))
    set_psi(batched, stack_psi(states, psi_names(policy)), (len(states),))
    propagator = parts.make_propagator(model, batched, parts.reward, angle_dims=parts.task.angle_dims)
    value = propagator.expected_return(parts.start, parts.task.horizon)
    grads = torch.autograd.grad(value.sum(), list(batched.parameters()))
    return value.detach(), list(grads)


def with_engine(parts: Any, **changes: Any) -> Any:
    """``parts`` whose engine (and so every propagator it makes) has ``changes``."""
    engine = parts.engine.replace(**changes)
    return dataclasses.replace(parts, engine=engine, make_propagator=functools.partial(parts.make_propagator,
                                                                                       engine=engine))


def max_relative(got: torch.Tensor, want: torch.Tensor) -> float:
    """max |got − want| / max |want|."""
    return float((got - want).abs().max() / want.abs().max())


def measure(experiment: str, repeats: int, seed: int) -> dict[str, Any]:
    """The preset's model past the sparse threshold, then one round timed both ways, alternately."""
    cfg = compose_stage(PRESETS[experiment], [])
    parts, model, n, fit_s = stage_model(cfg, seed)
    policy = parts.initial_policy()
    full_parts = with_engine(parts, lower_pairs=False)
    round_, restarts = batched_round(parts, model, policy, seed)
    rounds = {"full": batched_round(full_parts, model, policy, seed)[0], "lower": round_}
    times: dict[str, list[float]] = {"full": [], "lower": [], "full_cpu": [], "lower_cpu": []}
    for index in range(repeats + 1):  # the first of each is a warm-up
        for name in ("full", "lower"):
            tic, cpu = time.perf_counter(), time.process_time()
            rounds[name]()
            if index:
                times[name].append(time.perf_counter() - tic)
                times[f"{name}_cpu"].append(time.process_time() - cpu)
    value_full, grads_full = round_outputs(full_parts, model, policy, seed)
    value_lower, grads_lower = round_outputs(parts, model, policy, seed)
    # the torch twin: how far two correct evaluations of this round differ
    value_torch, grads_torch = round_outputs(with_engine(parts, moments="fused"), model, policy, seed)
    full_s, lower_s = statistics.median(times["full_cpu"]), statistics.median(times["lower_cpu"])
    outputs = int(parts.task.state_dim)
    return {"experiment": experiment, "task": parts.task.name, "outputs": outputs,
            "pairs": outputs * (outputs + 1) // 2, "horizon": parts.task.horizon, "n": n,
            "inducing": int(model.inducing_points.shape[0]) if hasattr(model, "inducing_points") else None,
            "fit_s": fit_s, "restarts": restarts, "full_s": full_s, "lower_s": lower_s, "ratio": lower_s / full_s,
            "full_wall_s": statistics.median(times["full"]), "lower_wall_s": statistics.median(times["lower"]),
            **{f"{name}_times": values for name, values in times.items()},
            "value_rel_diff": max_relative(value_lower, value_full),
            "grad_rel_diff": max(max_relative(g, f) for g, f in zip(grads_lower, grads_full, strict=True)),
            "torch_value_rel_diff": max_relative(value_full, value_torch),
            "torch_grad_rel_diff": max(max_relative(g, f) for g, f in zip(grads_full, grads_torch, strict=True))}


def vector_width() -> int:
    """Doubles per vector register the kernels are compiled for here (`-march=native`): 8, 4 or 2."""
    with contextlib.suppress(OSError), open("/proc/cpuinfo") as info:
        flags = next((line.split(":", 1)[1].split() for line in info if line.startswith("flags")), [])
        return 8 if "avx512f" in flags else 4 if "avx" in flags else 2
    return 2


def markdown(rows: list[dict[str, Any]], info: dict[str, Any]) -> str:
    """The section of docs/benchmarks.md."""
    lines = [
        "## Moment matching: the a = b pairs' exp sums from their lower triangles",
        "",
        f"`{info['command']}` at commit {info['commit']} — {info['date']}, {info['machine']['cpu']} "
        f"({info['machine']['cores']} cores), {info['threads']} torch thread(s), torch {info['machine']['torch']}; "
        f"{info['vector_width']} doubles per vector register (the kernels' lanes); "
        f"1-min load average {info['load_before']:.2f} before, {info['load_after']:.2f} after. "
        f"Results: `{info['output']}`.",
        "",
        "One policy-search round (rollout + gradient of the R restarts at once) on each preset's model just past "
        "`model.sparse_above` (the sparse GP, m inducing inputs), timed alternately with every output pair's full "
        "n x n exp sum (`Engine(lower_pairs=False)`, the form before) and with the a = b pairs' sums from their "
        f"lower triangles (the default); medians of {info['repeats']} after a warm-up of this process's CPU time "
        "(one thread: the work, whatever else shares the cores; wall times in the JSON). Ratio = lower / full, "
        "measured in the same run. Max rel. diff of V and of ∂V/∂ψ: lower against full, and (for scale: two correct "
        "evaluations of an ill-conditioned round) full against the torch twin (`kernels.moments=fused`).",
        "",
        markdown_table([[r["task"], r["outputs"], f"{r['pairs']} ({r['outputs']})", r["horizon"], r["inducing"],
                         r["restarts"], f"{r['full_s']:.3f}", f"{r['lower_s']:.3f}", f"{r['ratio']:.2f}×",
                         f"{r['value_rel_diff']:.1e}, {r['grad_rel_diff']:.1e}",
                         f"{r['torch_value_rel_diff']:.1e}, {r['torch_grad_rel_diff']:.1e}"] for r in rows],
                       ["task", "E", "pairs (a = b)", "H", "m", "R", "full (CPU s)", "lower (CPU s)", "ratio",
                        "lower vs full: V, ∂V/∂ψ", "full vs torch: V, ∂V/∂ψ"], "lrlrrrrrrll"),
    ]
    return "\n".join(lines)


def main() -> None:
    """Measure each preset's round both ways; write the JSON and (unless ``--no-docs``) the section."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experiments", nargs="+", choices=list(PRESETS), default=["cartpole", "mountaincar"])
    parser.add_argument("--threads", type=int, default=1, help="torch threads (a sweep job uses one)")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--seed", type=int, default=0, help="of the data collection, the fit and the restarts")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    parser.add_argument("--no-docs", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()[0]
    rows = []
    for experiment in args.experiments:
        rows.append(measure(experiment, args.repeats, args.seed))
        print({k: v for k, v in rows[-1].items() if not k.endswith("_times")}, file=sys.stderr, flush=True)
    output = args.output.resolve()
    info = {"date": today(), "command": command_line(), "commit": commit(),
            "machine": machine(), "vector_width": vector_width(), "threads": args.threads,
            "repeats": args.repeats, "seed": args.seed,
            "load_before": load_before, "load_after": os.getloadavg()[0], "output": display_path(output)}
    write_results(output, info, rows)
    section = markdown(rows, info)
    if not args.no_docs:
        write_section(SECTION, section)
    print(section)


if __name__ == "__main__":
    main()
