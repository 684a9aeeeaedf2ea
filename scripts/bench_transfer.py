"""Benchmark — qualitative transfer on cart-pole: 0.5 kg source → 2.0 kg target, PILCO vs the transfer approaches.

Per seed, the source is the 0.5 kg learning-loop benchmark's run of that seed
(``runs/bench_cartpole/cartpole/seed_<k>``, made by ``scripts/bench_cartpole.py``; created here with
the same command when missing). Every approach then learns the 2.0 kg target through the real CLI
with the same budget and overrides (the presets of ``qtl.report.APPROACHES``, named as in the paper); QTL runs
take θ_s and ψ_s from the seed's source. Reported per
approach: episodes to success (the task's criterion; the initial episode is 0), area under the
learning curve (trapezoid over the episodes), final performance (mean of the last 3 episodes)
and time to convergence (first episode at 95 % of it), mean ± std over seeds. Required: QTL
reaches success in fewer episodes than PILCO (median over seeds; a run that never succeeds
counts as the budget). Writes ``docs/bench/transfer.json`` and its table in ``docs/benchmarks.md``
(another ``--mass``: ``transfer-m<mass>.json`` and a section of its own).

The runs directory is laid out as an experiment directory (``target/<approach>/m<mass>/seed_<k>``, ``source``
a link to the sources), so ``qtl-report runs/bench_transfer`` writes the paper's Tables 1-3 and
Fig. 1 for it. Runs are deterministic and causal, so a finished run directory made by the same overrides is
reused rather than recomputed, and an interrupted one is resumed; extra arguments are Hydra
overrides for every target run.

    python scripts/bench_transfer.py [override ...] [--seeds 0 1 2 3 4] [--episodes 9] [--jobs 2]
        [--approaches pilco qtl_bayesian qtl_gamma_09 | all]
    python scripts/bench_transfer.py optimizer.restarts=1 --episodes 7 --approaches all  # the paper's 7 approaches
    python scripts/bench_transfer.py recipe=mc_pilco --tag particles --sources runs/bench_cartpole/cartpole-particles \
        --source-episodes 9 --source-overrides recipe=mc_pilco --approaches pilco qtl_bayesian  # particles
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
from pathlib import Path

from qtl.bench import (
    ROOT,
    command_line,
    commit,
    display_path,
    first_successes,
    machine,
    markdown_table,
    mean_std,
    parse_with_overrides,
    run_all,
    today,
    write_section,
)
from qtl.launch import ensure_run
from qtl.metrics import Curve
from qtl.recorder import TIMINGS_FILE
from qtl.report import (
    APPROACHES,
    DEFAULT_APPROACH,
    SEED_PREFIX,
    SOURCE_DIR,
    TARGET_DIR,
    ExperimentRecord,
    approach_name,
    approach_overrides,
)

DEFAULT_APPROACHES = ["pilco", "qtl_bayesian", "qtl_gamma_09"]  # the acceptance figure; --approaches all: the seven
SOURCE_EPISODES = 7  # learned episodes of a source run (bench_cartpole's default)
DEFAULT_MASS = 2.0  # kg, the paper's headline target


def link_experiment(runs_dir: Path, sources: Path) -> None:
    """Make ``runs_dir`` an experiment directory that ``qtl-report`` reads: ``source`` links to the sources."""
    link = runs_dir / SOURCE_DIR
    if not link.exists():
        link.symlink_to(sources.resolve(), target_is_directory=True)
    ExperimentRecord(name="cartpole transfer benchmark", commands=[command_line()]).write(runs_dir)


def result_names(mass: float, tag: str = "") -> tuple[str, str]:
    """The JSON file and docs section of a target mass (and ``--tag``): the headline 2.0 kg plain, others suffixed."""
    suffix = ("" if mass == DEFAULT_MASS else f"-m{mass:g}") + (f"-{tag}" if tag else "")
    return f"transfer{suffix}.json", f"bench_transfer{suffix}"


def main() -> None:
    """Make the sources, then every approach's target runs; judge the requirement, write the JSON and the section."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--episodes", type=int, default=9, help="learned episodes per target run (after 1 initial)")
    parser.add_argument("--mass", type=float, default=DEFAULT_MASS, help="target pole mass (kg)")
    parser.add_argument("--approaches", nargs="+", default=DEFAULT_APPROACHES, choices=[*APPROACHES, "all"])
    parser.add_argument("--jobs", type=int, default=2, help="runs in parallel (one torch thread each)")
    parser.add_argument("--sources", type=Path, default=ROOT / "runs" / "bench_cartpole" / "cartpole")
    parser.add_argument("--runs-dir", type=Path, help="default: runs/bench_transfer[-<tag>]")
    parser.add_argument("--source-episodes", type=int, default=SOURCE_EPISODES,
                        help="learned episodes of a source run (bench_cartpole's --within − 1)")
    parser.add_argument("--source-overrides", nargs="*", default=[],
                        help="Hydra overrides of the source runs, as bench_cartpole made them (e.g. recipe=mc_pilco)")
    parser.add_argument("--tag", default="", help="names the result files, section and runs directory (e.g. particles)")
    args, overrides = parse_with_overrides(parser)
    if args.runs_dir is None:
        args.runs_dir = ROOT / "runs" / ("bench_transfer" + (f"-{args.tag}" if args.tag else ""))
    approaches = [slug for slug in APPROACHES if slug in args.approaches or "all" in args.approaches]

    def source(seed: int) -> Path:
        return args.sources / f"{SEED_PREFIX}{seed}"

    def target_dir(slug: str, seed: int) -> Path:  # the layout of an experiment directory (qtl.report)
        return args.runs_dir / TARGET_DIR / slug / f"m{args.mass}" / f"{SEED_PREFIX}{seed}"

    def make_source(seed: int) -> float:
        return ensure_run([f"seed={seed}", f"episodes={args.source_episodes}", *args.source_overrides], source(seed),
                          args.source_episodes + 1)

    def target(job: tuple[str, int]) -> tuple[str, int, float]:
        slug, seed = job
        run_dir = target_dir(slug, seed)
        transfer = [f"transfer.source={source(seed)}"] if slug != DEFAULT_APPROACH else []
        run = [f"seed={seed}", f"episodes={args.episodes}", f"task.env.pole_mass={args.mass}", *overrides,
               *approach_overrides(slug), *transfer]
        return slug, seed, ensure_run(run, run_dir, args.episodes + 1)

    jobs = [(slug, seed) for seed in args.seeds for slug in approaches]  # seed-major: partial results pair up
    if any(slug != DEFAULT_APPROACH for slug in approaches):
        run_all(make_source, args.seeds, args.jobs)  # sources first: every QTL run of a seed reads its own
    walls = {(slug, seed): wall for slug, seed, wall in run_all(target, jobs, args.jobs)}

    link_experiment(args.runs_dir, args.sources)
    budget = args.episodes + 1
    results = {}
    for slug in approaches:
        per_seed = []
        for seed in args.seeds:
            run_dir = target_dir(slug, seed)
            curve = Curve.read(run_dir, budget)
            with open(run_dir / TIMINGS_FILE, newline="") as f:
                search = [float(t["policy_search_s"]) for t in csv.DictReader(f)][1:budget]
            per_seed.append({"seed": seed, "run_dir": display_path(run_dir), "returns": curve.returns,
                             "policy_search_s_per_episode": statistics.mean(search),
                             "successes": [int(s) for s in curve.successes], "compliance": curve.compliance,
                             "wall_s_this_call": walls[(slug, seed)], **curve.summary()})
        to_success = [r["first_success"] if r["first_success"] is not None else budget for r in per_seed]
        results[approach_name(slug)] = {"per_seed": per_seed,
                                        "median_episodes_to_success": statistics.median(to_success),
                                        "solved": sum(r["first_success"] is not None for r in per_seed)}
    baseline = approach_name(DEFAULT_APPROACH)
    judged = baseline in results and len(args.seeds) >= 5
    pilco = results.get(baseline, {}).get("median_episodes_to_success")
    passed = {name: r["median_episodes_to_success"] < pilco for name, r in results.items()
              if name.startswith("QTL") and pilco is not None} if judged else {}

    info = {"date": today(), "commit": commit(), "command": command_line(),
            "machine": machine(), "overrides": overrides, "episodes_per_run": budget,
            "target_pole_mass": args.mass, "sources": display_path(args.sources),
            "required": "QTL median episodes to success < PILCO's", "passed": passed,
            "results": results}
    json_name, section = result_names(args.mass, args.tag)
    out = ROOT / "docs" / "bench" / json_name
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(info, indent=2) + "\n")

    m = info["machine"]
    verdict = ("not judged: fewer than 5 seeds or no PILCO baseline" if not judged else
               "; ".join(f"{name}: {'met' if ok else 'NOT met'}" for name, ok in passed.items()))
    lines = [
        f"## Transfer: cart-pole 0.5 kg → {args.mass} kg" + (f" ({args.tag})" if args.tag else ""),
        "",
        f"`{info['command']}` at commit {info['commit']} — {info['date']}, {m['cpu']} ({m['cores']} cores), "
        f"{args.jobs} runs in parallel with 1 torch thread each, torch {m['torch']}. {budget} episodes per target "
        f"run (1 initial + {args.episodes} learned); sources: the 0.5 kg benchmark runs of the same seeds "
        f"({args.source_episodes + 1} episodes, "
        f"overrides: `{' '.join(args.source_overrides) or 'none'}`). Target overrides: "
        f"`{' '.join(overrides) or 'none'}`. Success: tip within 0.15 m of the "
        "target for the last 2 s; episode 0 is the initial one (random for PILCO, ψ_s for QTL). AUC: trapezoid "
        f"over the {budget} episodes. Results: `docs/bench/{out.name}`.",
        "",
        f"**Required: QTL's median episodes to success below PILCO's — {verdict}.**",
        "",
        f"A run that never succeeds counts as {budget} episodes (the budget) in the median: the median is then a lower "
        "bound. Compliance is Λ of Eq. 14 for the tuples of the last learned episode's model (QTL runs only).",
        "",
    ]
    rows = []
    for name, r in results.items():
        seeds = r["per_seed"]
        compliance = [s["compliance"][-1] for s in seeds if s["compliance"][-1] == s["compliance"][-1]]
        rows.append([name, first_successes(seeds), f"{r['median_episodes_to_success']:g}",
                     f"{r['solved']}/{len(seeds)}", mean_std([s["auc"] for s in seeds]),
                     mean_std([s["final_performance"] for s in seeds]),
                     mean_std([s["time_to_convergence"] for s in seeds]),
                     mean_std(compliance, 2) if compliance else "—",
                     mean_std([s["policy_search_s_per_episode"] for s in seeds])])
    lines.append(markdown_table(rows, ["approach", "first success per seed", "median episodes to success", "solved",
                                       "AUC", "final performance", "time to convergence", "compliance (last episode)",
                                       "policy search (s/episode)"], "llrrrrrrr"))
    lines += ["", "Returns per episode (seed: curve):", ""]
    for name, r in results.items():
        for s in r["per_seed"]:
            lines.append(f"- {name}, seed {s['seed']}: " + " ".join(f"{v:.1f}" for v in s["returns"]))
    write_section(section, "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
