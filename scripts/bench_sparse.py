"""Benchmark the model the loop uses as data grow: exact GP up to ``model.sparse_above`` tuples, sparse GP above.

For each n: n real transitions of the task (cart-pole unless ``task=`` is overridden; collected as
``bench_policy_search.py`` collects them), the dynamics model fitted as the loop fits it (``qtl.build``'s
``Parts.fit_dynamics``, default ``model=auto``; ``model.restarts`` overridable with ``--restarts``; exact GP for
n <= ``model.sparse_above``, SGPR with ``model.inducing`` above), then one moment-matching rollout + gradient over
the task's horizon with the loop's initial policy (median of ``--repeats`` after one warm-up). Above the threshold
the rollout's cost depends on the inducing inputs, not on n: the per-episode policy search stays flat. Writes JSON
(default ``docs/bench/sparse.json``) and, unless ``--no-docs``, its section of ``docs/benchmarks.md``.

    .venv/bin/python scripts/bench_sparse.py [--sizes 500 1000 2000 4000] [--restarts 1] [--threads 2]
        [--repeats 3] [--overrides OVERRIDE ...] [--output PATH] [--no-docs]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
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
    model_label,
    peak_rss_mib,
    today,
    write_results,
    write_section,
)
from qtl.bench.search import collect, compose_config, rollout_and_gradient
from qtl.build import build
from qtl.models import SparseDynamicsGP

SIZES = [500, 1000, 2000, 4000]
SECTION = "bench_sparse"
DEFAULT_OUTPUT = ROOT / "docs" / "bench" / "sparse.json"


def measure(n: int, restarts: int, repeats: int, seed: int, overrides: list[str]) -> dict:
    """Fit the loop's model on n tuples and time one rollout + gradient through it."""
    cfg = compose_config("moment_matching", "float64", [f"model.restarts={restarts}", *overrides])
    parts = build(cfg)
    task, start = parts.task, parts.start
    data = collect(task, int(cfg.task.policy_size), n, seed)
    tic = time.perf_counter()
    model = parts.fit_dynamics(data, torch.Generator().manual_seed(seed))
    fit_s = time.perf_counter() - tic
    propagator = parts.make_propagator(model, parts.initial_policy(), parts.reward, angle_dims=task.angle_dims)
    rollout_and_gradient(propagator, start, task.horizon)
    times = []
    for _ in range(repeats):
        tic = time.perf_counter()
        rollout_and_gradient(propagator, start, task.horizon)
        times.append(time.perf_counter() - tic)
    sparse = isinstance(model, SparseDynamicsGP)
    return {"task": task.name, "n": len(data), "model": "sparse" if sparse else "exact",
            "inducing": int(model.inducing_points.shape[0]) if sparse else None, "fit_s": fit_s,
            "fit_restarts": restarts, "rollout_grad_s_median": statistics.median(times),
            "sparse_above": cfg.model.get("sparse_above"), "horizon": task.horizon,
            "peak_rss_mib": peak_rss_mib()}


def markdown(results: list[dict], info: dict) -> str:
    """The section of docs/benchmarks.md."""
    lines = [
        "## Growing data: exact GP, then the sparse GP",
        "",
        f"`{info['command']}` at commit {info['commit']} — {info['date']}, {info['machine']['cpu']} "
        f"({info['machine']['cores']} cores), {info['threads']} torch threads, torch {info['machine']['torch']}. "
        "Transitions of the "
        f"{results[0]['task']} task, collected as in the policy-search benchmark; the model fitted as the loop "
        "fits it (default `model=auto`, "
        f"`model.restarts={info['restarts']}`), exact up to `model.sparse_above` tuples and SGPR with "
        "`model.inducing` learned inducing inputs above; one moment-matching rollout + gradient (H = "
        f"{results[0]['horizon']}, median of the repeats after a warm-up). The peak RSS is the process's so far. "
        f"Results: `{info['output']}`.",
        "",
        markdown_table([[r["n"], model_label(r), f"{r['fit_s']:.1f}", f"{r['rollout_grad_s_median']:.2f}",
                         f"{r['peak_rss_mib']:.0f}"] for r in results],
                       ["n", "model", "fit (s)", "rollout + gradient (s)", "peak RSS (MiB)"], "rlrrr"),
    ]
    return "\n".join(lines) + "\n"


def main() -> None:
    """Fit and time each size in turn; write the JSON and (unless ``--no-docs``) the section."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=SIZES)
    parser.add_argument("--restarts", type=int, default=1, help="model.restarts of every fit")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0, help="of the data collection and the fit")
    parser.add_argument("--overrides", nargs="*", default=[], help="Hydra overrides of the composed config")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    parser.add_argument("--no-docs", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    results = []
    for n in sorted(args.sizes):
        results.append(measure(n, args.restarts, args.repeats, args.seed, args.overrides))
        print(json.dumps(results[-1]), file=sys.stderr, flush=True)
    output = args.output.resolve()
    info = {"date": today(), "commit": commit(), "command": command_line(),
            "machine": machine(), "threads": args.threads, "restarts": args.restarts,
            "overrides": args.overrides,
            "output": display_path(output)}
    write_results(output, info, results)
    section = markdown(results, info)
    if not args.no_docs:
        write_section(SECTION, section)
    print(section)


if __name__ == "__main__":
    main()
