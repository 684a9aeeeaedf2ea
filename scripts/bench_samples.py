"""Benchmark — sample transfer (issue 65): PILCO, QTL Bayesian, QTL Bayesian + source samples, samples alone.

Settings (``--settings``, in this order by default): mountain car 100 % → 150 % and → 300 % power, cart-pole
0.5 kg → 1.0 kg and → 2.0 kg pole mass. Per setting and seed k, four arms learn the target through the real CLI:

- ``pilco``: no transfer;
- ``qtl_bayesian``: ``approach=qtl_bayesian`` (θ_s and ψ_s from the source, the Bayesian rule);
- ``qtl_bayesian_samples``: the same + ``transfer.samples=relevance`` (up to ``transfer.max_source_samples`` = 200
  source tuples in the target GP's data, each of noise σ²/w, w its relevance to the target's tuples);
- ``samples``: ``rule=none transfer.hyperparameters=false transfer.samples=relevance`` (samples alone: no θ_s,
  no ψ_s, a random initial episode).

The source of seed k: cart-pole, the 0.5 kg learning benchmark's run ``runs/bench_cartpole/cartpole/seed_<k>``
(``seed=k episodes=7``, made as ``bench_transfer.py`` makes it when missing); mountain car, a 1.0-power run made as
the mountain-car learning benchmark makes its runs (``bench_kinematic.py``'s delta arm: ``seed=k episodes=7
task=mountaincar propagation.integration=delta``), ``runs/bench_kinematic/mountaincar-delta/seed_<k>`` reused where
it was made by these overrides, else made under ``runs/bench_samples/sources/mountaincar``. Budgets: the family's
transfer benchmarks' recorded tables (mountain car 1 + 6 episodes as ``bench_compliance.py --learn``; cart-pole 1 + 7
with ``optimizer.restarts=1`` as ``bench_transfer.py``).

Reported per setting and arm: first success per seed (the task's own test; a run that never succeeds counts as the
budget), its mean, seeds solved, AUC (trapezoid over the episodes) and final performance, mean ± std; the last
episode's mean relevance and effective samples (sample arms); the model-fit and policy-search time per learned
episode (``timings.csv``: the fit cost of the larger dataset). Paired per seed: QTL Bayesian + samples against QTL
Bayesian (first success earlier / same / later), each sample arm's AUC minus PILCO's. Goals (issue 65): (a) at
cart-pole 1.0 kg, QTL Bayesian + samples succeeds earlier than QTL Bayesian in ≥ 4 of 5 paired seeds; (b) at mountain
car 300 %, the sample arms never learn worse than PILCO, taken per seed: each sample arm's AUC ≥ PILCO's − 5 % of
|PILCO's AUC| in every paired seed. Writes ``docs/bench/samples-<setting>.json`` and its section of
``docs/benchmarks.md`` per setting, as soon as the setting's runs are done.

Runs go under ``--runs-dir`` (``<setting>/<arm>/seed_<k>``). A finished run made by the same overrides is reused and an
interrupted one resumed (``qtl.launch``), so the same command completes the benchmark over several calls;
``--no-run`` writes the tables from the finished runs alone (the others marked not run). Extra arguments are Hydra
overrides for every target run.

    python scripts/bench_samples.py [--settings mountaincar-1.5 mountaincar-3.0 cartpole-1.0 cartpole-2.0]
        [--seeds 0 1 2 3 4] [--arms ...] [--episodes N] [--jobs 1] [--threads 1] [--no-run] [override ...]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import yaml

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
from qtl.bench.samples import (
    ARMS,
    GOAL_A_SETTING,
    GOAL_B_SETTING,
    SETTINGS,
    Setting,
    comparisons,
    goal_a,
    goal_b,
    run_result,
    section,
    status,
)
from qtl.launch import effective, ensure_run
from qtl.recorder import METRICS_FILE, TIMINGS_FILE

SOURCE_EPISODES = 7  # learned episodes of a source run (the learning benchmarks' --within 8)
CARTPOLE_SOURCES = ROOT / "runs" / "bench_cartpole" / "cartpole"  # bench_cartpole.py's 0.5 kg runs
MOUNTAINCAR_REUSED = ROOT / "runs" / "bench_kinematic" / "mountaincar-delta"  # bench_kinematic.py's delta runs


def source_run(task: str, seed: int, runs_dir: Path) -> tuple[Path, list[str]]:
    """The source run of ``seed`` for a task family and the overrides that make it (another benchmark's if it fits)."""
    if task == "cartpole":
        return CARTPOLE_SOURCES / f"seed_{seed}", [f"seed={seed}", f"episodes={SOURCE_EPISODES}"]
    overrides = [f"seed={seed}", f"episodes={SOURCE_EPISODES}", "task=mountaincar", "propagation.integration=delta"]
    reused = MOUNTAINCAR_REUSED / f"seed_{seed}"
    made_with = reused / ".hydra" / "overrides.yaml"
    if made_with.exists() and effective(yaml.safe_load(made_with.read_text())) == effective(overrides):
        return reused, overrides
    return runs_dir / "sources" / task / f"seed_{seed}", overrides


def finished(run_dir: Path, budget: int) -> bool:
    """Whether ``run_dir`` holds at least ``budget`` recorded episodes."""
    return all((run_dir / name).exists() and len(read_csv(run_dir / name)) >= budget
               for name in (METRICS_FILE, TIMINGS_FILE))


def bench_setting(setting: Setting, args: argparse.Namespace, overrides: list[str]) -> list[str]:
    """Run (unless ``--no-run``) every arm and seed of ``setting``; write its JSON and section. The failures."""
    episodes = setting.episodes if args.episodes is None else args.episodes
    budget = episodes + 1
    sources = {seed: source_run(setting.task, seed, args.runs_dir) for seed in args.seeds}

    def target_dir(arm: str, seed: int) -> Path:
        return args.runs_dir / setting.name / arm / f"seed_{seed}"

    def make_source(seed: int) -> str | None:
        run_dir, made_by = sources[seed]
        try:
            ensure_run(made_by, run_dir, SOURCE_EPISODES + 1, threads=args.threads)
        except Exception as err:  # reported with the others, the tables written first
            return f"source of seed {seed}: {err}"
        return None

    def target(job: tuple[str, int]) -> str | None:
        arm, seed = job
        run = setting.target_overrides(arm, seed, str(sources[seed][0]), [*overrides])
        if episodes != setting.episodes:
            run = [o for o in run if not o.startswith("episodes=")] + [f"episodes={episodes}"]
        if arm != "pilco" and not finished(sources[seed][0], SOURCE_EPISODES + 1):
            return f"{arm}, seed {seed}: no finished source"
        try:
            ensure_run(run, target_dir(arm, seed), budget, threads=args.threads)
        except Exception as err:  # reported with the others, the tables written first
            return f"{arm}, seed {seed}: {err}"
        return None

    failures: list[str] = []
    if not args.no_run:
        if any(arm != "pilco" for arm in args.arms):
            failures += [f for f in run_all(make_source, args.seeds, args.jobs) if f]
        jobs = [(arm, seed) for seed in args.seeds for arm in args.arms]  # seed-major: partial results pair up
        failures += [f for f in run_all(target, jobs, args.jobs) if f]

    arms: dict[str, list[dict[str, Any]]] = {}
    for arm in ARMS:  # the tables read every arm's finished runs, whichever --arms ran
        for seed in args.seeds:
            run_dir = target_dir(arm, seed)
            if finished(run_dir, budget):
                result = run_result(seed, read_csv(run_dir / METRICS_FILE), read_csv(run_dir / TIMINGS_FILE), budget)
                arms.setdefault(arm, []).append({"run_dir": display_path(run_dir), **result})
    goal = (goal_a(arms, budget) if setting.name == GOAL_A_SETTING else
            goal_b(arms) if setting.name == GOAL_B_SETTING else None)
    out = ROOT / "docs" / "bench" / f"samples-{setting.name}.json"
    source_dirs = sorted({display_path(run_dir.parent) for run_dir, _ in sources.values()})
    info = {"date": today(), "commit": commit(), "command": command_line(), "machine": machine(),
            "overrides": overrides, "setting": setting.name, "task": setting.task, "axis": setting.axis,
            "source_value": setting.source_value, "target_value": setting.target_value,
            "episodes_per_run": budget, "jobs": args.jobs, "threads": args.threads, "seeds": args.seeds,
            "sources": ", ".join(f"{d}/seed_<k>" for d in source_dirs), "output": display_path(out),
            "not_run": [f"{arm}, seed {seed}" for arm in ARMS for seed in args.seeds
                        if seed not in {r["seed"] for r in arms.get(arm, [])}],
            "goal": goal, "comparisons": comparisons(arms, budget), "arms": arms}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(info, indent=2) + "\n")
    lines = section(setting, info)
    write_section(f"bench_samples-{setting.name}", "\n".join(lines))
    print("\n".join(lines), flush=True)
    if goal is not None:
        print(f"{setting.name}: goal — {goal['goal']}: {status(goal['passed'])}", flush=True)
    return failures


def main() -> None:
    """Every setting in turn: its sources, its four arms per seed, its JSON and section; then the failures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--settings", nargs="+", choices=list(SETTINGS), default=list(SETTINGS))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--arms", nargs="+", choices=ARMS, default=list(ARMS),
                        help="run only these arms (the tables still read every arm's finished runs)")
    parser.add_argument("--episodes", type=int, help="learned episodes per target run (default: the setting's budget)")
    parser.add_argument("--jobs", type=int, default=1, help="runs in parallel")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per run")
    parser.add_argument("--runs-dir", type=Path, default=ROOT / "runs" / "bench_samples",
                        help="where the runs are made (and reused)")
    parser.add_argument("--no-run", action="store_true", help="only the tables, from the finished runs")
    args, overrides = parse_with_overrides(parser)
    args.arms = [arm for arm in ARMS if arm in args.arms]
    args.runs_dir = args.runs_dir.resolve()
    failures = []
    for name in [s for s in SETTINGS if s in args.settings]:
        failures += bench_setting(SETTINGS[name], args, overrides)
    if failures:
        print(f"{len(failures)} run(s) failed:\n" + "\n".join(f"  {f}" for f in failures), file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
