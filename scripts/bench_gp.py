"""Benchmark: DynamicsGP evidence maximisation, cold (PILCO's heuristic start) against warm (``model.warm_start``).

For each size n, in a fresh subprocess on 2 torch threads (E = 4 outputs of a D = 6 input smooth
function with noise, float64, the default budget of ``DynamicsGP.fit``):

- previous: one L-BFGS run on the same data less its last episode (the first n − T points),
  which gives θ_p_{i−1} and its objective as a run would hand them over (not timed as a fit);
- cold: today's fit on all n points, from the heuristic θ, ``restarts`` runs (the sizes of
  ``--cold-sizes`` only: at n = 2000 it alone takes ~9 minutes on the dev VM);
- warm: ``DynamicsGP.fit_warm`` from the previous θ_p, cold restarts only for the outputs it leaves short.

Objectives are log evidence + log prior per data point, mean over the E outputs. Writes
``docs/bench/gp.json`` and the GP section of ``docs/benchmarks.md``.

    python scripts/bench_gp.py [--sizes 250 500 1000 2000] [--cold-sizes 250 500 1000] [--threads 2]
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

from qtl.bench import (
    ROOT,
    commit,
    display_path,
    machine,
    markdown_table,
    peak_rss_mib,
    relative_token,
    today,
    write_results,
    write_section,
)

INPUT_DIM, OUTPUTS = 6, 4
NOISE_STD = 0.05
EPISODE = 50  # T: points of the last episode (the cart-pole horizon)
EVIDENCE_EVALS = 5
COLD_2000_S = 541.9  # the cold fit at n = 2000, measured by this script on 2026-11-21 (docs/bench/gp.json then)


def run_one(n: int, threads: int, seed: int, cold: bool) -> dict:
    """Fit one GP of size n cold and warm in this process; return the figures."""
    import torch

    from qtl.models import DynamicsGP, PreviousFit
    from qtl.models.gp_evidence import DEFAULT_MAX_ITER, DEFAULT_RESTARTS, WARM_RESTART_TOLERANCE

    torch.set_num_threads(threads)
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(n, INPUT_DIM, generator=gen, dtype=torch.float64) * 4 - 2
    w = torch.randn(INPUT_DIM, OUTPUTS, generator=gen, dtype=torch.float64)
    y = torch.sin(x @ w / 2) + NOISE_STD * torch.randn(n, OUTPUTS, generator=gen, dtype=torch.float64)

    runs = {"count": 0}  # L-BFGS runs, counted around the model's one-run method
    one_run = DynamicsGP._optimise

    def counted(model: DynamicsGP, max_iter: int) -> torch.Tensor:
        runs["count"] += 1
        return one_run(model, max_iter)

    DynamicsGP._optimise = counted  # type: ignore[method-assign]
    baseline = peak_rss_mib()

    tic = time.perf_counter()
    before = DynamicsGP(x[:-EPISODE], y[:-EPISODE])
    before.fit(restarts=1)
    previous = PreviousFit.of(before)
    previous_s = time.perf_counter() - tic

    row: dict = {"n": n, "E": OUTPUTS, "D": INPUT_DIM, "T": EPISODE, "restarts": DEFAULT_RESTARTS,
                 "max_iter": DEFAULT_MAX_ITER, "tolerance": WARM_RESTART_TOLERANCE, "previous_fit_s": previous_s,
                 "previous_objective": previous.objective.tolist()}
    if cold:
        model = DynamicsGP(x, y)
        runs["count"] = 0
        tic = time.perf_counter()
        value = model.fit(generator=torch.Generator().manual_seed(seed))
        row.update(cold_s=time.perf_counter() - tic, cold_objective=value.tolist(), cold_runs=runs["count"])

    model = DynamicsGP(x, y)
    runs["count"] = 0
    tic = time.perf_counter()
    value = model.fit_warm(previous.theta, previous.objective, generator=torch.Generator().manual_seed(seed))
    row.update(warm_s=time.perf_counter() - tic, warm_objective=value.tolist(), warm_runs=runs["count"])

    row.update(evidence_and_grad_s=evidence_and_grad_s(model), rss_before_fit_mib=baseline)
    # Restarts as a leading batch dimension: R restarts stacked as R·E outputs of one batched GP, per evaluation.
    stacked = DynamicsGP(x, y.repeat(1, DEFAULT_RESTARTS))
    row.update(stacked_restarts_eval_s=evidence_and_grad_s(stacked),
               sequential_restarts_eval_s=DEFAULT_RESTARTS * row["evidence_and_grad_s"],
               peak_rss_mib=peak_rss_mib())
    return row


def evidence_and_grad_s(model: object) -> float:
    """Seconds per evaluation of the summed objective and its gradient (after one warm-up)."""
    model.train()
    for k in range(EVIDENCE_EVALS + 1):
        if k == 1:
            tic = time.perf_counter()
        model.zero_grad()
        (-model.log_evidence().sum()).backward()
    return (time.perf_counter() - tic) / EVIDENCE_EVALS


def mean(values: list[float]) -> float:
    """Mean of a list of floats."""
    return sum(values) / len(values)


def table(rows: list[dict]) -> str:
    """The markdown table of the results."""
    cells = []
    for r in rows:
        cold = ([f"{r['cold_s']:.1f}", f"{r['warm_s']:.1f}", f"{r['cold_s'] / r['warm_s']:.1f}x",
                 f"{r['cold_runs']} / {r['warm_runs']}", f"{mean(r['cold_objective']):.4f}"] if "cold_s" in r else
                ["—", f"{r['warm_s']:.1f}", "—", f"— / {r['warm_runs']}", "—"])
        cells.append([r["n"], *cold, f"{mean(r['warm_objective']):.4f}", f"{mean(r['previous_objective']):.4f}",
                      f"{r['evidence_and_grad_s']:.3f}",
                      f"{r['sequential_restarts_eval_s']:.3f} / {r['stacked_restarts_eval_s']:.3f}",
                      f"{r['peak_rss_mib']:.0f}"])
    return markdown_table(cells, [
        "n", "cold fit (s)", "warm fit (s)", "cold / warm", "L-BFGS runs cold / warm", "objective cold",
        "objective warm", "objective previous (n − T)", "log evidence + gradient (s)",
        "R restarts: sequential / stacked (s)", "peak RSS (MiB)"], "r" * 11)


def evidence(rows: list[dict]) -> str:
    """One paragraph: how the warm objective compares with the previous fit's and the cold fit's, per output."""
    over_previous = [w - p for r in rows for w, p in zip(r["warm_objective"], r["previous_objective"], strict=True)]
    cold_gain = [c - w for r in rows if "cold_s" in r
                 for c, w in zip(r["cold_objective"], r["warm_objective"], strict=True)]
    restarted = sum(r["warm_runs"] > 1 for r in rows)
    text = (f"Per output, the warm objective lay {min(over_previous):+.4f} to {max(over_previous):+.4f} per point "
            f"from the previous fit's (the restart rule's reference; tolerance {rows[0]['tolerance']})")
    if cold_gain:
        text += f", and the cold fit beat it by at most {max(cold_gain):+.5f} per point"
    text += f"; cold restarts ran at {restarted} of {len(rows)} sizes."
    ratios = [r["stacked_restarts_eval_s"] / r["sequential_restarts_eval_s"] for r in rows]
    text += (f" Stacking the restarts as one batch took {min(ratios):.2f}-{max(ratios):.2f}x the time of running "
             "them one after another, per evaluation")
    if min(ratios) >= 0.8:
        return text + (": the cost is the E·R Cholesky factorisations either way, and one L-BFGS over the stack "
                       "would share its line searches, so the restarts stay sequential (the warm fit seldom runs any).")
    return text + "."


def main() -> None:
    """Fit each size in its own subprocess (or one size, as that subprocess); write the JSON and the section."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[250, 500, 1000, 2000])
    parser.add_argument("--cold-sizes", type=int, nargs="*", default=[250, 500, 1000])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--machine", default=None, help="how the machine is named in the docs (default: lscpu's)")
    parser.add_argument("--output", type=Path, default=ROOT / "docs" / "bench" / "gp.json")
    parser.add_argument("--no-docs", action="store_true", help="do not rewrite the section of docs/benchmarks.md")
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # child process: one size
    parser.add_argument("--cold", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--docs-only", action="store_true", help="rewrite the docs section from --output only")
    args = parser.parse_args()
    if args.docs_only:
        saved = json.loads(args.output.read_text())
        write_docs(saved, saved.pop("results"), args.output)
        return
    if args.one is not None:
        print(json.dumps(run_one(args.one, args.threads, args.seed, args.cold)))
        return

    rows = []
    load = os.getloadavg()[0]
    for n in args.sizes:
        child = [sys.executable, __file__, "--one", str(n), "--threads", str(args.threads), "--seed", str(args.seed)]
        out = subprocess.run(child + (["--cold"] if n in args.cold_sizes else []),
                             capture_output=True, text=True, check=True).stdout
        rows.append(json.loads(out.strip().splitlines()[-1]))
        r = rows[-1]
        cold = f"cold {r['cold_s']:.1f} s ({mean(r['cold_objective']):.4f}), " if "cold_s" in r else ""
        print(f"n={n}: {cold}warm {r['warm_s']:.1f} s ({mean(r['warm_objective']):.4f}), "
              f"{r['warm_runs']} warm L-BFGS run(s)", flush=True)

    command = " ".join(["python", "scripts/bench_gp.py", *(shlex.quote(relative_token(token))
                                                          for token in sys.argv[1:])])
    info = {"date": today(), "command": command, "commit": commit(),
            "machine": machine(),
            "machine_name": args.machine, "threads": args.threads, "load_average_at_start": load}
    write_results(args.output, info, rows)
    if not args.no_docs:
        write_docs(info, rows, args.output)


def write_docs(info: dict, rows: list[dict], output: Path) -> None:
    """The GP section of ``docs/benchmarks.md`` from the results."""
    m = info["machine"]
    name = info["machine_name"] or f"{m['cpu']} ({m['cores']} cores)"
    lines = [
        "## GP dynamics model: evidence maximisation, cold and warm",
        "",
        f"`{info['command']}` at commit {info['commit']} — {info['date']}, {name}, {info['threads']} torch threads, "
        f"torch {m['torch']}, float64, load average {info['load_average_at_start']:.2f} at the start. "
        f"E = {OUTPUTS} outputs, D = {INPUT_DIM} inputs, {rows[0]['restarts']} restarts × ≤ {rows[0]['max_iter']} "
        f"L-BFGS iterations, exact Cholesky throughout. Results: `{display_path(output)}`.",
        "",
        "*Cold* is today's default fit (`model.warm_start=false`): PILCO's heuristic θ, then the perturbed "
        f"restarts. *Warm* (`model.warm_start=true`) starts from θ_p of the same data less its last episode "
        f"(T = {EPISODE} points, fitted by one L-BFGS run, as the previous episode of a run hands it over) and "
        "runs the cold restarts only for outputs whose objective falls more than `WARM_RESTART_TOLERANCE` below "
        "that previous fit's. Objectives: log evidence + log prior per point, mean over outputs (higher is better). "
        "The last columns time one evaluation of objective and gradient for the R restarts one after another "
        "(R × the E-output batch) and stacked as one R·E-output batch (a leading restart dimension).",
        "",
        table(rows),
        "",
        evidence(rows),
    ]
    if any("cold_s" not in r for r in rows):
        lines += ["", "Cold fits run at the `--cold-sizes` only (the default leaves out n = 2000, where the cold fit "
                  f"alone took {COLD_2000_S} s in this script's run of 2026-11-21 on the same VM)."]
    write_section("bench_gp", "\n".join(lines))


if __name__ == "__main__":
    main()
