"""Benchmark — source choice (issue 65): a library of sources, transfer.select=compliance|mixture, each source alone.

Per family (``--families``), a library of sources along the task's transfer axis, one run per value (seed 0,
learned from scratch through the real CLI with the family's learning budget) and a target value:

- cart-pole: pole masses 0.5, 1.0 and 3.0 kg, target 2.0 kg (the 0.5 kg source is ``bench_cartpole.py``'s
  run of seed 0, ``runs/bench_cartpole/cartpole/seed_0``, reused where its overrides compose the same config);
- mountain car: power 50 %, 100 % and 300 %, target 150 %.

Per target seed (``--seeds``), each arm learns the target through the CLI: ``transfer.select=compliance`` and
``transfer.select=mixture`` over the library, each source alone, all with the ``qtl_bayesian`` preset (θ_s and ψ_s
transferred, as ``bench_transfer.py``'s QTL Bayesian), and PILCO. Required: select=compliance picks the source
nearest the target in at least 4 of 5 seeds, nearest by **log distance** |log(v / target)|, i.e. by ratio: for
the cart-pole 1.0 kg and 3.0 kg tie by |Δ| (1.0 kg each from 2.0 kg), while 3.0 / 2.0 = 1.5 < 2.0 / 1.0 = 2.0 makes
3.0 kg the nearest; for the mountain car 100 % (ratio 1.5) is nearer 150 % than 300 % (ratio 2.0), and |Δ|
agrees. The choice (``selected_source`` k, mapped to the k-th value of the library) and Λ_k (``compliance/<k>``) are
read from the compliance arm's ``metrics.csv``. Goal: that arm's mean AUC at least the mean of the single-source
arms'. Reported per arm: first success per seed (the task's own test), AUC (trapezoid over the episodes) and
final performance, mean ± std. Writes ``docs/bench/sources-<family>.json`` and its section of ``docs/benchmarks.md``.

Runs go under ``--runs-dir`` (``<family>/source/<axis><value>/seed_0``, ``<family>/target/<arm>/seed_<k>``). A
finished run made by the same overrides is reused and an interrupted one resumed (``qtl.launch``), so the same
command completes the benchmark over several calls; ``--no-run`` writes the tables from the finished runs alone
(the others marked not run). Extra arguments are Hydra overrides for every target run.

    python scripts/bench_sources.py [--families mountaincar cartpole] [--seeds 0 1 2 3 4] [--episodes N]
        [--source-episodes N] [--jobs 1] [--threads 1] [--arms ARM ...] [--no-run] [override ...]
    python scripts/bench_sources.py --families cartpole --arms compliance  # the required check's runs first
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import yaml
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from qtl.bench import (
    ROOT,
    command_line,
    commit,
    display_path,
    machine,
    parse_with_overrides,
    read_csv,
    run_all,
    today,
    write_section,
)
from qtl.bench.sources import (
    FAMILIES,
    Family,
    arm_overrides,
    arms,
    resume_command,
    section,
    seed_result,
    selection_verdict,
    single_arm,
)
from qtl.bench.sources import goal_verdict as judge_goal
from qtl.config import register_configs
from qtl.launch import effective, ensure_run
from qtl.recorder import METRICS_FILE


def composed(overrides: list[str]) -> str:
    """The ``train`` config that ``overrides`` compose (what a run computes: the neutral overrides left out), YAML."""
    register_configs()
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        return OmegaConf.to_yaml(compose(config_name="train", overrides=effective(overrides)))


def library(family: Family, runs_dir: Path, source_episodes: int) -> dict[float, tuple[Path, list[str]]]:
    """Per library value, its run directory and the overrides that make it (another benchmark's run where it fits)."""
    family = replace(family, source_episodes=source_episodes)  # a reused run fits only if made with this budget
    found = {}
    for value in family.sources:
        own = family.source_overrides(value)
        reuse = family.reused(value)
        if reuse is not None and composed(reuse[1]) == composed(own):
            found[value] = (ROOT / reuse[0], reuse[1])
        else:
            found[value] = (family.source_dir(runs_dir, value), own)
    return found


def threads_of(run_dir: Path) -> int | None:
    """The torch threads a run was made with (its recorded ``threads=`` override), None if not recorded."""
    made_with = run_dir / ".hydra" / "overrides.yaml"
    if not made_with.exists():
        return None
    found = [o.split("=", 1)[1] for o in yaml.safe_load(made_with.read_text()) if o.startswith("threads=")]
    return int(found[-1]) if found and found[-1].isdigit() else None


def selected_arms(family: Family, names: list[str]) -> set[str]:
    """The arms ``--arms`` names: slugs as they are, a number as the arm of the library's source at that value."""
    chosen = set()
    for name in names:
        try:
            chosen.add(single_arm(family, float(name)))
        except ValueError:
            chosen.add(name)
    return chosen


def finished_rows(run_dir: Path, budget: int) -> list[dict[str, str]] | None:
    """A run's metrics rows if it has ``budget`` episodes, else None (not run, or unfinished)."""
    path = run_dir / METRICS_FILE
    if not path.exists():
        return None
    rows = read_csv(path)
    return rows if len(rows) >= budget else None


def benchmark(name: str, args: argparse.Namespace, overrides: list[str]) -> bool:
    """Make (or resume) the family's runs, then write its JSON and section from the finished ones; True if all ran."""
    family = FAMILIES[name]
    episodes = family.episodes if args.episodes is None else args.episodes
    source_episodes = family.source_episodes if args.source_episodes is None else args.source_episodes
    budget = episodes + 1
    sources = library(family, args.runs_dir, source_episodes)
    paths = [str(sources[v][0]) for v in family.sources]

    def target_dir(arm: str, seed: int) -> Path:
        return args.runs_dir / family.task / "target" / arm / f"seed_{seed}"

    def make_source(value: float) -> float:
        run_dir, made_by = sources[value]
        return ensure_run(made_by, run_dir, source_episodes + 1, threads=args.threads)

    def make_target(job: tuple[str, int]) -> float:
        arm, seed = job
        return ensure_run(arm_overrides(family, arm, seed, episodes, paths, overrides), target_dir(arm, seed), budget,
                          threads=args.threads)

    error = None
    if not args.no_run:
        try:
            run_all(make_source, list(family.sources), args.jobs)
            chosen = [arm for arm in arms(family) if args.arms is None or arm in selected_arms(family, args.arms)]
            run_all(make_target, [(arm, seed) for seed in args.seeds for arm in chosen], args.jobs)  # seed-major
        except RuntimeError as err:  # a failed run: what finished is still reported, the rest marked not run
            error = err

    results: dict[str, list] = {}
    unfinished = []
    for arm in arms(family):
        for seed in args.seeds:
            rows = finished_rows(target_dir(arm, seed), budget)
            if rows is None:
                unfinished.append(f"{arm}/seed_{seed}")
                continue
            result = seed_result(seed, rows, budget, family.sources)
            result["run_dir"] = display_path(target_dir(arm, seed))
            results.setdefault(arm, []).append(result)
    out = ROOT / "docs" / "bench" / f"sources-{name}.json"
    resume = resume_command(command_line())
    info = {"date": today(), "commit": commit(), "command": command_line(), "machine": machine(),
            "overrides": overrides, "jobs": args.jobs, "threads": args.threads, "seeds": args.seeds,
            "episodes_per_run": budget, "source_episodes_per_run": source_episodes + 1,
            "target": family.target, "axis": family.axis, "library": list(family.sources),
            "sources": {f"{v:g}": display_path(sources[v][0]) for v in family.sources},
            "source_overrides": {f"{v:g}": sources[v][1] for v in family.sources},
            "source_reused": {f"{v:g}": sources[v][1] != replace(family, source_episodes=source_episodes
                                                                  ).source_overrides(v) for v in family.sources},
            "source_threads": {f"{v:g}": threads_of(sources[v][0]) for v in family.sources},
            "source_finished": {f"{v:g}": finished_rows(sources[v][0], source_episodes + 1) is not None
                                for v in family.sources},
            "output": display_path(out),
            "selection": selection_verdict(family, results.get("compliance", []), args.seeds),
            "goal": judge_goal(family, results, args.seeds),
            "unfinished": unfinished, "resume": resume if unfinished else None,
            "error": None if error is None else str(error).replace(f"{ROOT}/", ""),  # no path of this machine
            "results": results}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(info, indent=2) + "\n")
    lines = section(family, info)
    write_section(f"bench_sources-{name}", "\n".join(lines))
    print("\n".join(lines), flush=True)
    if error is not None:
        print(f"{name}: {error}", file=sys.stderr)
    return error is None and not unfinished


def main() -> None:
    """Every family in turn: its library, its target runs, its verdicts, JSON and section."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", nargs="+", choices=list(FAMILIES), default=list(FAMILIES))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4], help="target seeds")
    parser.add_argument("--episodes", type=int, help="learned episodes per target run (default: the family's)")
    parser.add_argument("--source-episodes", type=int, help="learned episodes per source run (default: the family's)")
    parser.add_argument("--jobs", type=int, default=1, help="runs in parallel")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per run")
    parser.add_argument("--runs-dir", type=Path, default=ROOT / "runs" / "bench_sources")
    parser.add_argument("--arms", nargs="+", metavar="ARM",
                        help="run only these arms (compliance, mixture, pilco, or a library value for that source "
                             "alone, e.g. 0.5); the tables still read every arm's finished runs")
    parser.add_argument("--no-run", action="store_true",
                        help="make no run: the tables from the finished runs alone, the others marked not run")
    args, overrides = parse_with_overrides(parser)
    complete = [benchmark(name, args, overrides) for name in args.families]
    sys.exit(0 if all(complete) else 1)


if __name__ == "__main__":
    main()
