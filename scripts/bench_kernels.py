"""Benchmark the fused exp sum Σ_ij W_ij exp((A Bᵀ)_ij): the torch path against the native kernel, in one run.

At the sizes moment matching uses (P = 10 output pairs, K = 8, n = 250, 500, 1000; alone and with
R = 3 restarts batched over a broadcast W `P x n x n`): the forward pass, and forward plus the
gradients for A and B (W fixed, as for the GP dynamics; the native forward then forms them too).
Then one moment-matching rollout plus its policy gradient at n = 250 (E = 4, GP input 6-D;
`bench_rollout.py`'s case) under each backend.
Medians of the repeats after one warm-up, 2 torch threads. Writes `docs/bench/kernels.json` and
its section of `docs/benchmarks.md`.

    .venv/bin/python scripts/bench_kernels.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Callable

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
from qtl.kernels import Engine, weighted_exp_sum
from qtl.kernels.native import build as native_build

PAIRS = 10  # E(E+1)/2 for E = 4 outputs
FEATURES = 8  # K = D + 2 for D = 6 GP inputs
SIZES = (250, 500, 1000)
RESTARTS = (1, 3)
ROLLOUT_N = 250
THREADS = 2
BACKENDS = ("torch", "native")
MACHINE = "2-core dev VM"
OUTPUT = ROOT / "docs" / "bench" / "kernels.json"


def problem(n: int, restarts: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A, B `[R x] P x n x K` (entries ~ N(0, 0.3²)) and a signed W `P x n x n`, float64."""
    gen = torch.Generator().manual_seed(n + restarts)
    batch = (PAIRS,) if restarts == 1 else (restarts, PAIRS)
    a = 0.3 * torch.randn(*batch, n, FEATURES, generator=gen, dtype=torch.float64)
    b = 0.3 * torch.randn(*batch, n, FEATURES, generator=gen, dtype=torch.float64)
    w = torch.randn(PAIRS, n, n, generator=gen, dtype=torch.float64)
    return a, b, w


def median_time(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time of ``fn`` over ``repeats`` calls after one warm-up call, seconds."""
    fn()
    times = []
    for _ in range(repeats):
        tic = time.perf_counter()
        fn()
        times.append(time.perf_counter() - tic)
    return statistics.median(times)


def bench_exp_sum(n: int, restarts: int, repeats: int) -> dict:
    """Forward and forward + backward times of both backends on one problem."""
    a, b, w = problem(n, restarts)
    a_req, b_req = a.clone().requires_grad_(), b.clone().requires_grad_()

    row: dict = {"n": n, "restarts": restarts, "pairs": PAIRS, "k": FEATURES}
    for name in BACKENDS:
        engine = Engine.resolve(name, "reference")

        def forward(engine: Engine = engine) -> torch.Tensor:
            return weighted_exp_sum(a, b, w, engine=engine)

        def forward_backward(engine: Engine = engine) -> tuple[torch.Tensor, ...]:
            return torch.autograd.grad(weighted_exp_sum(a_req, b_req, w, engine=engine).sum(), (a_req, b_req))

        row[f"{name}_forward_ms"] = 1e3 * median_time(forward, repeats)
        row[f"{name}_forward_backward_ms"] = 1e3 * median_time(forward_backward, repeats)
        row[f"{name}_value"] = forward()
    row["max_rel_diff"] = float(((row["native_value"] - row["torch_value"]).abs() / row["torch_value"].abs()).max())
    del row["native_value"], row["torch_value"]
    for what in ("forward", "forward_backward"):
        row[f"{what}_speedup"] = row[f"torch_{what}_ms"] / row[f"native_{what}_ms"]
    return row


def bench_rollout_gradient(repeats: int) -> dict:
    """One moment-matching rollout (H = 50) plus the policy gradient at n = ROLLOUT_N, both backends."""
    row: dict = {"n": ROLLOUT_N, "horizon": HORIZON}
    for name in BACKENDS:
        propagator, start = make_case(ROLLOUT_N, torch.float64, Engine.resolve(name, "reference"))
        row[f"{name}_s"] = median_time(lambda: rollout_and_gradient(propagator, start, HORIZON), repeats)  # noqa: B023
        row[f"{name}_value"] = rollout_and_gradient(propagator, start, HORIZON)
    row["speedup"] = row["torch_s"] / row["native_s"]
    return row


def markdown(info: dict, rows: list[dict], rollout: dict) -> str:
    """The section of docs/benchmarks.md."""
    lines = [
        "## Fused exp sum: torch path vs native kernel",
        "",
        f"Σ_ij W_ij exp((A Bᵀ)_ij) at moment matching's sizes: P = {PAIRS} output pairs, K = {FEATURES}, "
        "A and B `[R x] P x n x K`, W `P x n x n` (broadcast over R restarts), float64; "
        "forward, and forward plus the gradients for A and B (W fixed, as for the GP dynamics: the native "
        "kernel then forms them in its forward pass, and its backward is two products). "
        f"Median of {info['repeats']} after one warm-up, {THREADS} torch threads, both backends in one run. "
        "Speed-up = torch time / native time.",
        "",
        f"Command: `{info['command']}`  ",
        f"Date: {info['date']}  ",
        f"Machine: {info['machine']} ({info['cpu']}), torch {info['torch']}, commit {info['commit']}; "
        f"1-min load average {info['load_average_1min'][0]} before, {info['load_average_1min'][1]} after "
        "(other work on the machine slows the torch path's threads most)  ",
        f"Results: `{info['output']}`",
        "",
        markdown_table([[r["n"], r["restarts"], f"{r['torch_forward_ms']:.2f}", f"{r['native_forward_ms']:.2f}",
                         f"{r['forward_speedup']:.2f}×", f"{r['torch_forward_backward_ms']:.2f}",
                         f"{r['native_forward_backward_ms']:.2f}", f"{r['forward_backward_speedup']:.2f}×",
                         f"{r['max_rel_diff']:.1e}"] for r in rows],
                       ["n", "R", "forward torch (ms)", "forward native (ms)", "speed-up", "fwd + bwd torch (ms)",
                        "fwd + bwd native (ms)", "speed-up", "max rel. diff"], "r" * 9),
    ]
    lines += [
        "",
        f"One moment-matching rollout (H = {rollout['horizon']}) plus the policy gradient at n = {rollout['n']} "
        "(E = 4, GP input 6-D, `bench_rollout.py`'s case): "
        f"torch {rollout['torch_s']:.3f} s, native {rollout['native_s']:.3f} s ({rollout['speedup']:.2f}×); "
        f"V = {rollout['torch_value']:.12f} (torch) and {rollout['native_value']:.12f} (native).",
    ]
    return "\n".join(lines)


def main() -> None:
    """Build (or find) the native kernel, time both backends, write JSON and the markdown section."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(THREADS)
    native_build.build()
    load_before = os.getloadavg()[0]
    rows = []
    for n in SIZES:
        for restarts in RESTARTS:
            rows.append(bench_exp_sum(n, restarts, args.repeats))
            print(rows[-1], file=sys.stderr)
    rollout = bench_rollout_gradient(max(3, args.repeats // 2))
    print(rollout, file=sys.stderr)
    measured_on = machine()
    info = {
        "date": today(),
        "command": command_line(),
        "machine": MACHINE,
        "cpu": measured_on["cpu"],
        "torch": measured_on["torch"],
        "threads": THREADS,
        "repeats": args.repeats,
        "commit": commit(),
        "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        "output": display_path(OUTPUT),
    }
    write_results(OUTPUT, {**info, "rollout": rollout}, rows)
    section = markdown(info, rows, rollout)
    write_section("bench_kernels", section)
    print(section)


if __name__ == "__main__":
    main()
