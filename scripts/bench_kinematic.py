"""Benchmark — kinematic against full-state moment matching, learning from scratch (issue 63).

For each ``--tasks`` task (one that declares ``task.kinematics``), runs the real CLI (``python -m qtl task=<task>``)
once per seed under ``propagation.integration=delta`` (the GP models every output) and once under ``speed`` (the GP
models the non-position outputs, the positions follow their velocities by the task's ``kinematics.scheme``), in
parallel processes of ``--threads`` torch threads, and reports both arms per seed in one table: the episode of first
success (the task's own test), the learning curve and the time per episode. Required of ``speed``: success within
``--within`` episodes (the random one included) in at least 4 of 5 seeds, and a median first success no later than
``delta``'s (a seed that never succeeds counts as later than any that does). Writes
``docs/bench/kinematic-<task>.json`` and its table in ``docs/benchmarks.md``. Extra arguments are Hydra overrides for
every run. Finished run directories made by the same overrides are reused and interrupted ones resumed
(``qtl.launch``), so a long benchmark can be completed over several calls.

    python scripts/bench_kinematic.py [--tasks mountaincar cartpole] [--seeds 0 1 2 3 4] [--within 8] [--jobs 2]
        [--threads 1] [override ...]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
from typing import Any

from qtl.bench import (
    ROOT,
    add_learning_arguments,
    command_line,
    commit,
    machine,
    markdown_table,
    parse_with_overrides,
    run_all,
    run_seed,
    today,
    write_section,
)
from qtl.bench.search import compose_config
from qtl.build import build

INTEGRATIONS = ("delta", "speed")  # full state (the baseline), kinematic
REQUIRED_EPISODES = 8  # success within this many episodes, the random one included (--within)
REQUIRED_SEEDS = 4  # in at least this many of ...
JUDGED_SEEDS = 5  # ... this many seeds; fewer seeds make a partial run that is not judged


def median_first_success(results: list[dict[str, Any]]) -> float:
    """The median episode of first success over seeds, a seed without one counted as never (inf)."""
    return statistics.median(math.inf if r["first_success"] is None else r["first_success"] for r in results)


def judge(arms: dict[str, list[dict[str, Any]]], within: int) -> dict[str, Any]:
    """The requirement on ``speed`` against ``delta``: seeds solved within ``within``, median first successes."""
    solved = [r for r in arms["speed"] if r["first_success"] is not None and r["first_success"] < within]
    medians = {name: median_first_success(results) for name, results in arms.items()}
    judged = len(arms["speed"]) >= JUDGED_SEEDS and len(arms["delta"]) == len(arms["speed"])
    passed = (len(solved) >= REQUIRED_SEEDS and medians["speed"] <= medians["delta"]) if judged else None
    return {"solved": len(solved), "seeds": len(arms["speed"]), "median_first_success": medians, "passed": passed}


def _episode(value: float) -> str:
    """A median first success as the table shows it."""
    return "never" if math.isinf(value) else f"{value:g}"


def section(task: str, info: dict[str, Any]) -> list[str]:
    """The Markdown section of one task: the settings, the verdict and both arms per seed."""
    m, verdict, within = info["machine"], info["verdict"], info["within"]
    status = {True: "met", False: "NOT met", None: "not judged: a partial run"}[verdict["passed"]]
    medians = verdict["median_first_success"]
    rows = [[r["seed"], name, "—" if r["first_success"] is None else r["first_success"],
             f"{sum(r['successes'][1:])} of {len(r['successes']) - 1}",
             " ".join(f"{v:.1f}" for v in r["returns"]), f"{r['model_fit_s_per_episode']:.1f}",
             f"{r['policy_search_s_per_episode']:.1f}"]
            for name in INTEGRATIONS for r in info["arms"][name]]
    return [
        f"## Kinematic vs full-state moment matching from scratch: {task}",
        "",
        f"`{info['command']}` at commit {info['commit']} — {info['date']}, {m['cpu']} ({m['cores']} cores), "
        f"{info['jobs']} run(s) in parallel with {info['threads']} torch thread(s) each, torch {m['torch']}. "
        f"{info['episodes_per_run']} episodes per seed (1 random + {info['episodes_per_run'] - 1} learned); success "
        f"is the task's own test. `delta`: the GP models every output; `speed`: the non-position outputs, the "
        f"positions integrated ({info['kinematics']}). Results: `{info['output']}`.",
        "",
        f"**Required of speed: success within {within} episodes in at least {REQUIRED_SEEDS} of {JUDGED_SEEDS} seeds, "
        f"and a median first success no later than delta's — {status} ({verdict['solved']} of {verdict['seeds']} "
        f"seeds succeeded; median first success {_episode(medians['speed'])} (speed) vs "
        f"{_episode(medians['delta'])} (delta)).**",
        "",
        markdown_table(rows, ["seed", "integration", "first success (episode, 0 = random)",
                              "successful learned episodes", "returns per episode", "model fit (s/episode)",
                              "policy search (s/episode)"], "rllrrrr"),
    ]


def main() -> None:
    """Run both arms of every task (reusing or resuming runs), judge, write the JSON and the sections."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["mountaincar"], help="tasks that declare task.kinematics")
    add_learning_arguments(parser, seeds=[0, 1, 2, 3, 4], within=REQUIRED_EPISODES,
                           runs_dir=ROOT / "runs" / "bench_kinematic")
    args, overrides = parse_with_overrides(parser)
    episodes = args.within - 1 if args.episodes is None else args.episodes

    for task in args.tasks:
        jobs = [(name, seed) for name in INTEGRATIONS for seed in args.seeds]
        results = run_all(lambda job, task=task: run_seed(
            job[1], episodes, args.runs_dir / f"{task}-{job[0]}" / f"seed_{job[1]}",
            [f"task={task}", f"propagation.integration={job[0]}", *overrides], args.threads), jobs, args.jobs)
        arms = {name: [r for (arm, _), r in zip(jobs, results, strict=True) if arm == name] for name in INTEGRATIONS}
        out = ROOT / "docs" / "bench" / f"kinematic-{task}.json"
        kinematics = declared_kinematics(task)
        info = {"date": today(), "commit": commit(), "command": command_line(), "machine": machine(),
                "overrides": overrides, "episodes_per_run": episodes + 1, "jobs": args.jobs, "threads": args.threads,
                "within": args.within, "kinematics": kinematics, "output": str(out.relative_to(ROOT)),
                "verdict": judge(arms, args.within), "arms": arms}
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(info, indent=2) + "\n")
        lines = section(task, info)
        write_section(f"bench_kinematic-{task}", "\n".join(lines))
        print("\n".join(lines))


def declared_kinematics(task: str) -> str:
    """The task's declared kinematics in words: positions ← velocities, the scheme and T."""
    kin = build(compose_config("moment_matching", "float64", [f"task={task}", "propagation.integration=speed"])
                ).task.kinematics
    pairs = ", ".join(f"{p} ← {v}" for p, v in zip(kin.positions, kin.velocities, strict=True))
    return f"dims {pairs}, T = {kin.period:g}, w = {kin.weight:g}"


if __name__ == "__main__":
    main()
