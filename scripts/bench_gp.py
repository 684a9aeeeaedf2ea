"""Benchmark: DynamicsGP evidence maximisation, fit time and peak memory against dataset size.

Each size runs in a fresh subprocess (so peak memory is its own), on 2 torch threads, E = 4
outputs of a D = 6 input smooth function with noise, float64, the default fit (restarts and
L-BFGS iterations of ``DynamicsGP.fit``). Writes ``docs/bench/gp.json`` and the table in
``docs/benchmarks.md``.

    python scripts/bench_gp.py [--sizes 250 500 1000 2000] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import benchlib

INPUT_DIM, OUTPUTS = 6, 4
NOISE_STD = 0.05


def run_one(n: int, threads: int, seed: int) -> dict:
    """Fit one GP of size n in this process; return its figures."""
    import torch

    from qtl.models import DynamicsGP
    from qtl.models.dynamics_gp import DEFAULT_MAX_ITER, DEFAULT_RESTARTS

    torch.set_num_threads(threads)
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(n, INPUT_DIM, generator=gen, dtype=torch.float64) * 4 - 2
    w = torch.randn(INPUT_DIM, OUTPUTS, generator=gen, dtype=torch.float64)
    y = torch.sin(x @ w / 2) + NOISE_STD * torch.randn(n, OUTPUTS, generator=gen, dtype=torch.float64)
    model = DynamicsGP(x, y)
    baseline = benchlib.peak_rss_mib()
    start = time.perf_counter()
    model.fit(generator=torch.Generator().manual_seed(seed))
    seconds = time.perf_counter() - start
    model.train()
    evals = 5
    start = time.perf_counter()
    for _ in range(evals):
        model.zero_grad()
        (-model.log_evidence().sum()).backward()
    per_eval = (time.perf_counter() - start) / evals
    return {
        "n": n,
        "E": OUTPUTS,
        "D": INPUT_DIM,
        "restarts": DEFAULT_RESTARTS,
        "max_iter": DEFAULT_MAX_ITER,
        "fit_s": seconds,
        "evidence_and_grad_s": per_eval,
        "peak_rss_mib": benchlib.peak_rss_mib(),
        "rss_before_fit_mib": baseline,
        "noise_std_learned": model.hyperparameters.noise_variance.sqrt().tolist(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[250, 500, 1000, 2000])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # child process: one size
    args = parser.parse_args()
    if args.one is not None:
        print(json.dumps(run_one(args.one, args.threads, args.seed)))
        return

    rows = []
    for n in args.sizes:
        out = subprocess.run(
            [sys.executable, __file__, "--one", str(n), "--threads", str(args.threads), "--seed", str(args.seed)],
            capture_output=True, text=True, check=True,
        ).stdout
        rows.append(json.loads(out.strip().splitlines()[-1]))
        print(f"n={n}: fit {rows[-1]['fit_s']:.1f} s, peak RSS {rows[-1]['peak_rss_mib']:.0f} MiB", flush=True)

    info = {"date": benchlib.today(), "command": benchlib.command_line(), "machine": benchlib.machine(),
            "threads": args.threads, "results": rows}
    out_path = benchlib.ROOT / "docs" / "bench" / "gp.json"
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(json.dumps(info, indent=2) + "\n")

    m = info["machine"]
    lines = [
        "## GP dynamics model: evidence maximisation",
        "",
        f"`{info['command']}` — {info['date']}, {m['cpu']} ({m['cores']} cores), {args.threads} torch threads, "
        f"torch {m['torch']}, float64. E = {OUTPUTS} outputs, D = {INPUT_DIM} inputs, default fit "
        f"({rows[0]['restarts']} restarts × ≤ {rows[0]['max_iter']} L-BFGS iterations), exact Cholesky throughout. "
        "Results: `docs/bench/gp.json`.",
        "",
        "| n | fit time (s) | log evidence + gradient (s) | peak RSS (MiB) | RSS before fit (MiB) |",
        "| ---: | ---: | ---: | ---: | ---: |",
    ]
    lines += [
        f"| {r['n']} | {r['fit_s']:.1f} | {r['evidence_and_grad_s']:.3f} | {r['peak_rss_mib']:.0f} | "
        f"{r['rss_before_fit_mib']:.0f} |"
        for r in rows
    ]
    benchlib.write_section("bench_gp", "\n".join(lines))


if __name__ == "__main__":
    main()
