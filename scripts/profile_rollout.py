"""Where one moment-matching rollout + gradient spends its time: torch.profiler, per kernels setting.

    .venv/bin/python scripts/profile_rollout.py [--n 250] [--threads 2] [--rows 15] [--kernels native/native ...]
        [--integration delta speed]
    .venv/bin/python scripts/profile_rollout.py --experiment aircraft_source [--threads 1] [override ...]

On the model and ψ_0 that `scripts/bench_policy_search.py` times (its cached cart-pole model of n tuples,
fitted first if missing), for each ``backend/moments`` pair of ``kernels.backend`` and ``kernels.moments``:
and each ``--integration`` (``propagation.integration``: ``delta``, or ``speed``, kinematic moment matching):
the median wall time of a rollout + gradient (after warm-ups), then one profiled rollout + gradient: the
number of profiled operations (aten ops, autograd nodes and the native autograd Functions) and the rows
that take the most self CPU time. With ``--experiment``, the same for one round of that full-scale preset's
policy search as `scripts/bench_scale.py` times it (the rollout + gradient of its R restarts at once, on the
model fitted to the task's own transitions just past ``model.sparse_above``; Hydra overrides after the
options, e.g. ``task.horizon=50`` for a shorter round). Prints Markdown; writes nothing.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable

import torch
from torch.profiler import ProfilerActivity, profile

from qtl.bench import markdown_table, model_label, parse_with_overrides
from qtl.bench.scale import compose_stage, model_facts, stage_model
from qtl.bench.search import CACHE_DIR, batched_round, compose_config, ensure_model, rollout_and_gradient
from qtl.build import build
from qtl.models import DynamicsGP

WARMUPS, REPEATS = 2, 7


def profile_call(call: Callable[[], float | None], heading: str, rows: int) -> str:
    """The median wall time of ``call`` (after warm-ups) and the table of one profiled call, as Markdown."""
    for _ in range(WARMUPS):
        call()
    times = []
    for _ in range(REPEATS):
        tic = time.perf_counter()
        value = call()
        times.append(time.perf_counter() - tic)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        call()
    events = prof.key_averages()
    total = sum(e.self_cpu_time_total for e in events)
    shown = "" if value is None else f" (V = {value:.6f})"
    lines = [
        heading,
        "",
        f"Rollout + gradient: median {statistics.median(times):.3f} s of {REPEATS}{shown}; "
        f"profiled: {sum(e.count for e in events)} operations, {total / 1e3:.1f} ms self CPU (profiler included).",
        "",
        markdown_table([[event.key, event.count, f"{event.self_cpu_time_total / 1e3:.1f}",
                         f"{event.self_cpu_time_total / total:.0%}"]
                        for event in sorted(events, key=lambda e: e.self_cpu_time_total, reverse=True)[:rows]],
                       ["operation", "calls", "self CPU (ms)", "share"], "lrrr"),
    ]
    return "\n".join(lines)


def profile_setting(backend: str, moments: str, n: int, rows: int, integration: str = "delta") -> str:
    """The timing and profile table of one ``kernels`` setting and ``propagation.integration``, as Markdown."""
    cfg = compose_config("moment_matching", "float64", [f"kernels.backend={backend}", f"kernels.moments={moments}",
                                                       f"propagation.integration={integration}"])
    path, _ = ensure_model(cfg, n, 0, CACHE_DIR)
    parts = build(cfg)
    model = DynamicsGP.load(path, dtype=parts.dtype, device=parts.device)
    propagator = parts.make_propagator(model, parts.initial_policy(), parts.reward, angle_dims=parts.task.angle_dims)
    return profile_call(lambda: rollout_and_gradient(propagator, parts.start, parts.task.horizon),
                        f"### kernels.backend={backend} kernels.moments={moments} propagation.integration="
                        f"{integration}, n = {n}", rows)


def profile_experiment(preset: str, overrides: list[str], rows: int, seed: int = 0) -> str:
    """The timing and profile table of one search round of a full-scale preset's stage, as Markdown."""
    cfg = compose_stage(preset, overrides)
    parts, model, n, _ = stage_model(cfg, seed)
    round_, restarts = batched_round(parts, model, parts.initial_policy(), seed)
    heading = (f"### experiment={preset}: one search round, R = {restarts}, H = {parts.task.horizon}, n = {n}, "
               f"{model_label(model_facts(model))}")
    return profile_call(round_, heading, rows)


def main() -> None:
    """Command line: profile each ``--kernels`` setting in turn, or one round of ``--experiment``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=250, help="GP training tuples")
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    parser.add_argument("--rows", type=int, default=15, help="table rows per setting")
    parser.add_argument("--kernels", nargs="+", default=["torch/reference", "native/native"],
                        metavar="BACKEND/MOMENTS", help="kernels.backend/kernels.moments settings to profile")
    parser.add_argument("--integration", nargs="+", default=["delta"], choices=["delta", "speed"],
                        help="propagation.integration of the cart-pole profile (speed: kinematic moment matching)")
    parser.add_argument("--experiment", metavar="PRESET",
                        help="profile one search round of this full-scale preset (e.g. aircraft_source) instead")
    args, overrides = parse_with_overrides(parser)
    settings = [tuple(k.split("/")) for k in args.kernels]
    if any(len(s) != 2 for s in settings):
        parser.error("--kernels takes BACKEND/MOMENTS pairs, e.g. native/native")
    if overrides and not args.experiment:
        parser.error(f"Hydra overrides ({' '.join(overrides)}) need --experiment: the cart-pole profile takes none")
    torch.set_num_threads(args.threads)
    print(f"`python scripts/profile_rollout.py {' '.join(sys.argv[1:])}`".replace(" `", "`") + "\n")
    if args.experiment:
        print(profile_experiment(args.experiment, overrides, args.rows), "\n", flush=True)
        return
    for backend, moments in settings:
        for integration in args.integration:
            print(profile_setting(backend, moments, args.n, args.rows, integration), "\n", flush=True)


if __name__ == "__main__":
    main()
