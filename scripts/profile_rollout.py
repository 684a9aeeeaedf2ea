"""Where one moment-matching rollout + gradient spends its time: torch.profiler, per kernels setting.

    .venv/bin/python scripts/profile_rollout.py [--n 250] [--threads 2] [--rows 15] [--kernels native/native ...]

On the model and ψ_0 that `scripts/bench_policy_search.py` times (its cached cart-pole model of n tuples,
fitted first if missing), for each ``backend/moments`` pair of ``kernels.backend`` and ``kernels.moments``:
the median wall time of a rollout + gradient (after warm-ups), then one profiled rollout + gradient: the
number of profiled operations (aten ops, autograd nodes and the native autograd Functions) and the rows
that take the most self CPU time. Prints Markdown; writes nothing.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_policy_search as bps  # the benchmark's model and config, shared

from qtl.build import build
from qtl.models import DynamicsGP

WARMUPS, REPEATS = 2, 7


def rollout_and_gradient(propagator, parts) -> float:
    """One V = Σ E[r(x_t)] and its ∂V/∂ψ (the objective of one search evaluation); returns V."""
    propagator.policy.zero_grad()
    value = propagator.expected_return(parts.start, parts.task.horizon)
    value.backward()
    return value.item()


def profile_setting(backend: str, moments: str, n: int, rows: int) -> str:
    """The timing and profile table of one ``kernels`` setting, as Markdown."""
    cfg = bps.compose_config("moment_matching", "float64", [f"kernels.backend={backend}", f"kernels.moments={moments}"])
    path, _ = bps.ensure_model(cfg, n, 0, bps.CACHE_DIR)
    parts = build(cfg)
    model = DynamicsGP.load(path, dtype=parts.dtype, device=parts.device)
    propagator = parts.make_propagator(model, parts.initial_policy(), parts.reward, angle_dims=parts.task.angle_dims)
    for _ in range(WARMUPS):
        rollout_and_gradient(propagator, parts)
    times = []
    for _ in range(REPEATS):
        tic = time.perf_counter()
        value = rollout_and_gradient(propagator, parts)
        times.append(time.perf_counter() - tic)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        rollout_and_gradient(propagator, parts)
    events = prof.key_averages()
    total = sum(e.self_cpu_time_total for e in events)
    lines = [
        f"### kernels.backend={backend} kernels.moments={moments}, n = {n}",
        "",
        f"Rollout + gradient: median {statistics.median(times):.3f} s of {REPEATS} (V = {value:.6f}); "
        f"profiled: {sum(e.count for e in events)} operations, {total / 1e3:.1f} ms self CPU (profiler included).",
        "",
        "| operation | calls | self CPU (ms) | share |",
        "| --- | ---: | ---: | ---: |",
    ]
    for event in sorted(events, key=lambda e: e.self_cpu_time_total, reverse=True)[:rows]:
        share = event.self_cpu_time_total / total
        lines.append(f"| {event.key} | {event.count} | {event.self_cpu_time_total / 1e3:.1f} | {share:.0%} |")
    return "\n".join(lines)


def main() -> None:
    """Command line: profile each ``--kernels`` setting in turn."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=250, help="GP training tuples")
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    parser.add_argument("--rows", type=int, default=15, help="table rows per setting")
    parser.add_argument("--kernels", nargs="+", default=["torch/reference", "native/native"],
                        metavar="BACKEND/MOMENTS", help="kernels.backend/kernels.moments settings to profile")
    args = parser.parse_args()
    settings = [tuple(k.split("/")) for k in args.kernels]
    if any(len(s) != 2 for s in settings):
        parser.error("--kernels takes BACKEND/MOMENTS pairs, e.g. native/native")
    torch.set_num_threads(args.threads)
    print(f"`python scripts/profile_rollout.py {' '.join(sys.argv[1:])}`".replace(" `", "`") + "\n")
    for backend, moments in settings:
        print(profile_setting(backend, moments, args.n, args.rows), "\n", flush=True)


if __name__ == "__main__":
    main()
