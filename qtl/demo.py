"""``qtl-demo``: the paper's story in one command — a 0.5 kg source run, then QTL to a 2.0 kg cart-pole.

1. PILCO learns the 0.5 kg swing-up from scratch (the source task);
2. QTL-PILCO Bayesian learns the 2.0 kg target from it (θ_s and ψ_s transferred), and PILCO
   learns the same target from scratch beside it (``--no-baseline`` skips it);
3. a side-by-side summary: episodes to success, area under the learning curve, final
   performance, task compliance.

Runs go to ``<out>/source``, ``<out>/target_qtl_bayesian`` and ``<out>/target_pilco`` (each a
normal ``qtl-train`` run directory for TensorBoard); a finished run is reused and an interrupted
one resumed when the command is repeated. Extra arguments are Hydra overrides for every run.
"""

from __future__ import annotations

import argparse
import math
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from qtl.launch import ensure_run
from qtl.metrics import Curve
from qtl.report.tables import markdown_table


def summary_table(runs: dict[str, Path]) -> str:
    """Markdown table of each run's learning-curve summary, side by side."""
    rows = []
    for name, run_dir in runs.items():
        curve = Curve.read(run_dir)
        s = curve.summary()
        first = "—" if s["first_success"] is None else str(s["first_success"])
        compliance = curve.compliance[-1]
        shown = "—" if math.isnan(compliance) else f"{compliance:.2f}"
        rows.append([name, len(curve.returns), first, f"{s['auc']:.1f}", f"{s['final_performance']:.1f}", shown])
    return markdown_table(rows, ["run", "episodes", "first success", "area under curve", "final performance",
                                 "compliance (last)"])


def main() -> None:
    """Source run, transfer run (and PILCO baseline), summary."""
    parser = argparse.ArgumentParser(prog="qtl-demo", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("outputs/demo"), help="where the runs go")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--episodes", type=int, default=9, help="learned episodes per run (after 1 initial)")
    parser.add_argument("--mass", type=float, default=2.0, help="target pole mass (kg)")
    parser.add_argument("--no-baseline", action="store_true", help="skip PILCO from scratch on the target")
    args, overrides = parser.parse_known_args()
    out = args.out.expanduser().resolve()
    common = [f"seed={args.seed}", f"episodes={args.episodes}", *overrides]
    total = args.episodes + 1

    source = out / "source"
    print(f"[1/2] source: PILCO on the 0.5 kg cart-pole -> {source}", flush=True)
    ensure_run(common, source, total, threads=2)  # alone on the machine: both cores

    target = [*common, f"task.env.pole_mass={args.mass}"]
    jobs = {f"target {args.mass} kg, QTL Bayesian": (
        [*target, "approach=qtl_bayesian", f"transfer.source={source}"], out / "target_qtl_bayesian")}
    if not args.no_baseline:
        jobs[f"target {args.mass} kg, PILCO"] = (target, out / "target_pilco")
    print(f"[2/2] target: {', '.join(jobs)} -> {out}", flush=True)
    threads = 2 if len(jobs) == 1 else 1  # two runs side by side share the cores
    with ThreadPoolExecutor(max_workers=len(jobs)) as pool:
        list(pool.map(lambda job: ensure_run(job[0], job[1], total, threads=threads), jobs.values()))

    runs = {"source 0.5 kg, PILCO": source, **{name: run_dir for name, (_, run_dir) in jobs.items()}}
    print("\n" + summary_table(runs))
    print(f"\nEpisode 0 is the initial one (random actions; the source policy for QTL). "
          f"TensorBoard: tensorboard --logdir {out}")


if __name__ == "__main__":
    main()
