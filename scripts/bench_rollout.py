"""Benchmark one moment-matching rollout plus its policy gradient (H = 50, E = 4, GP input 6).

Cart-pole shape: state [x, ẋ, θ, θ̇] with θ an angle, GP input [x, ẋ, θ̇, sin θ, cos θ, u], an
RBF policy with 50 basis functions squashed to ±10 N, the tip-distance reward. Each
configuration (n, dtype) runs in a fresh subprocess so that its peak resident memory
(``resource.getrusage`` max RSS) is its own. Writes JSON (default ``docs/bench/rollout.json``)
and its section of ``docs/benchmarks.md``. ``--dense`` is the ablation without the blocked kernel sums.

    .venv/bin/python scripts/bench_rollout.py [--sizes 250 500 1000] [--repeats 3] [--dense]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
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
    today,
    write_results,
    write_section,
)
from qtl.bench.search import rollout_and_gradient
from qtl.bench.synthetic import HORIZON, make_case
from qtl.build import DTYPES
from qtl.kernels import moments as kernel_moments
from qtl.kernels.engine import DEFAULT_ENGINE, Engine

THREADS = int(os.environ.get("BENCH_THREADS", "2"))
DESCRIPTION = (
    "One moment-matching rollout of H = 50 steps plus the gradient of V w.r.t. the policy parameters ψ "
    "(`MomentMatching.expected_return(...).backward()`), cart-pole shape: E = 4 outputs, GP input "
    "[x, ẋ, θ̇, sin θ, cos θ, u] (6-D), RBF policy with 50 basis functions squashed to ±10, tip-distance "
    "reward. Each configuration runs in a fresh subprocess; \"peak RSS\" is its `getrusage` max RSS "
    "(includes torch/GPyTorch and the model), \"setup RSS\" the same before the first rollout. Times are "
    "medians of the repeats after one warm-up."
)
DENSE_DESCRIPTION = (
    "Ablation: the `n x n` kernel sums as plain autograd ops (whole matrices, kept for backward at every "
    "step) instead of the blocked, recomputing `weighted_exp_sum`."
)
BENCH_DIR = ROOT / "docs" / "bench"


def dense_weighted_exp_sum(a: torch.Tensor, b: torch.Tensor, w: torch.Tensor, block_rows: int | None = None,
                           engine: Engine = DEFAULT_ENGINE) -> torch.Tensor:
    """Ablation: Σ W ∘ exp(A Bᵀ) as plain autograd ops on the whole `n x n` matrices."""
    return (w * torch.exp(a @ b.mT)).sum((-2, -1))


def worker(n: int, dtype_name: str, repeats: int, dense: bool = False) -> dict:
    """Measure one configuration in this process."""
    torch.set_num_threads(THREADS)
    if dense:
        kernel_moments.weighted_exp_sum = dense_weighted_exp_sum
    propagator, start = make_case(n, DTYPES[dtype_name])
    rss_setup = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    value = rollout_and_gradient(propagator, start, HORIZON)  # warm-up
    times = []
    for _ in range(repeats):
        tic = time.perf_counter()
        rollout_and_gradient(propagator, start, HORIZON)
        times.append(time.perf_counter() - tic)
    forward = []
    for _ in range(repeats):
        tic = time.perf_counter()
        with torch.no_grad():
            propagator.expected_return(start, HORIZON)
        forward.append(time.perf_counter() - tic)
    rss_peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return {
        "n": n,
        "dtype": dtype_name,
        "horizon": HORIZON,
        "value": value,
        "rollout_grad_s_median": statistics.median(times),
        "rollout_grad_s_min": min(times),
        "rollout_only_s_median": statistics.median(forward),
        "peak_rss_mib": rss_peak / 1024,
        "setup_rss_mib": rss_setup / 1024,
        "repeats": repeats,
        "variant": "dense" if dense else "blocked",
    }


def markdown(results: list[dict], info: dict, dense: bool) -> str:
    """The section of docs/benchmarks.md."""
    m = info["machine"]
    title = "## Rollout (moment matching)" if not dense else "## Rollout (moment matching): dense ablation"
    intro = DESCRIPTION if not dense else DENSE_DESCRIPTION
    lines = [
        title,
        "",
        intro,
        "",
        f"`{info['command']}` at commit {info['commit']} — {info['date']}, {m['cpu']} ({m['cores']} cores), "
        f"{THREADS} torch threads, torch {m['torch']}. Results: `{info['output']}`.",
        "",
        markdown_table([[r["n"], r["dtype"], r["variant"], f"{r['rollout_grad_s_median']:.2f}",
                         f"{r['rollout_only_s_median']:.2f}", f"{r['peak_rss_mib']:.0f}", f"{r['setup_rss_mib']:.0f}",
                         f"{r['value']:.4f}"] for r in results],
                       ["n", "dtype", "variant", "rollout + gradient (s, median)", "rollout only (s)",
                        "peak RSS (MiB)", "setup RSS (MiB)", "V"], "rllrrrrr"),
    ]
    return "\n".join(lines)


def main() -> None:
    """Run every configuration in its own subprocess; write JSON, print markdown."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[250, 500, 1000])
    parser.add_argument("--dtypes", nargs="+", default=list(DTYPES), choices=list(DTYPES))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--output", type=Path, help="JSON path (default docs/bench/rollout[_dense].json)")
    parser.add_argument(
        "--dense",
        action="store_true",
        help="ablation: the n x n kernel sums as plain autograd ops (no blocking, n² autograd memory per step)",
    )
    parser.add_argument("--worker", nargs=2, metavar=("N", "DTYPE"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(worker(int(args.worker[0]), args.worker[1], args.repeats, args.dense)))
        return
    results = []
    for n in args.sizes:
        for dtype_name in args.dtypes:
            cmd = [sys.executable, __file__, "--worker", str(n), dtype_name, "--repeats", str(args.repeats)]
            cmd += ["--dense"] if args.dense else []
            out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
            results.append(json.loads(out.strip().splitlines()[-1]))
            print(json.dumps(results[-1]), file=sys.stderr)
    output = args.output or BENCH_DIR / ("rollout_dense.json" if args.dense else "rollout.json")
    info = {"date": today(), "commit": commit(), "command": command_line(),
            "machine": machine(), "output": display_path(output)}
    write_results(output, info, results)
    section = markdown(results, info, args.dense)
    write_section("bench_rollout_dense" if args.dense else "bench_rollout", section)
    print(section)

if __name__ == "__main__":
    main()
