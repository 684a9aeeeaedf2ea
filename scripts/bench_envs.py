"""Benchmark — the shipped examples of envs that are not ours learn with the default learner.

Runs each example task (``configs/task/pendulum.yaml``, ``mountaincar_continuous.yaml``,
``inverted_pendulum.yaml``) through the real CLI (``python -m qtl task=<name>``: PILCO, moment
matching, the default optimiser) for each seed, in parallel processes of ``--threads`` torch threads,
and reports per example and seed the episode of first success (the task's own test, stated in the
table), the learning curve, the episode lengths (episodes end early where the env terminates) and the
time spent learning. Required (issue 20): each example succeeds within 10 episodes, the random one
included, in at least 2 of 3 seeds. Writes ``docs/bench/envs.json`` and its table in
``docs/benchmarks.md``; the results of examples not run in this call are kept from the previous
file, so ``--envs`` can fill the table one example at a time. Extra arguments are Hydra overrides
for every run. Finished run directories made by the same overrides are reused and interrupted ones
resumed (``qtl.launch``, as ``bench_cartpole.py``), so the benchmark can be completed over several calls.

    python scripts/bench_envs.py [--envs pendulum ...] [--seeds 0 1 2] [--within 10] [--jobs 2] [--threads 1]
        [override ...]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
from pathlib import Path
from typing import Any

import yaml

from qtl.bench import (
    ROOT,
    add_learning_arguments,
    command_line,
    commit,
    machine,
    markdown_table,
    parse_with_overrides,
    read_csv,
    run_all,
    run_seed,
    today,
    write_section,
)
from qtl.recorder import METRICS_FILE, TIMINGS_FILE

EXAMPLES = ("pendulum", "mountaincar_continuous", "inverted_pendulum")  # configs/task/<name>.yaml
# What each example's success test means in the env's terms (the numbers come from the run's own config).
MEANINGS = {
    "pendulum": "d = chord from the tip to upright, so d <= 0.2 is |θ| <= ~0.2 rad",
    "mountaincar_continuous": "d = |position − 0.5|: the goal (x >= 0.45, where the env terminates) reached",
    "inverted_pendulum": "d = sqrt((x/2)² + θ²): pole within ~0.1 rad, cart within ~0.2 m; a fallen pole never counts",
}
REQUIRED_EPISODES = 10  # success within this many episodes, the random one included (--within)
REQUIRED_SEEDS = 2  # in at least this many of ...
JUDGED_SEEDS = 3  # ... this many seeds; fewer seeds make a partial result that is not judged
RESULTS = ROOT / "docs" / "bench" / "envs.json"
SECTION = "bench_envs"


def success_test(task: dict[str, Any]) -> str:
    """The success test of a run's composed ``task`` config, in words."""
    success, repeat = task["success"], task.get("action_repeat", 1)
    held = f", each step {repeat} env steps" if repeat != 1 else ""
    return (f"distance to the target in the reward's metric <= {success['threshold']:g} for the last "
            f"{success['last_steps']} of {task['horizon']} steps{held}")


def describe_run(run_dir: Path, budget: int) -> dict[str, Any]:
    """What :func:`qtl.bench.run_seed` does not read: lengths, the env's own returns, learning time, success test."""
    rows = read_csv(run_dir / METRICS_FILE)[:budget]
    timings = read_csv(run_dir / TIMINGS_FILE)[:budget]
    task = yaml.safe_load((run_dir / ".hydra" / "config.yaml").read_text())["task"]
    return {
        "lengths": [int(r["length"]) for r in rows],
        "env_returns": [float(r["env_return"]) for r in rows],  # the env's own reward, logged beside the task's
        "learning_s": sum(float(t["model_fit_s"]) + float(t["policy_search_s"]) for t in timings),
        "success_test": success_test(task),
    }


def verdict(per_seed: list[dict[str, Any]], within: int, budget: int) -> dict[str, Any]:
    """How many seeds succeeded within ``within`` episodes, and whether the requirement is met.

    None (not judged) for fewer than JUDGED_SEEDS seeds or runs of fewer than ``within`` episodes (``budget``).
    """
    solved = sum(r["first_success"] is not None and r["first_success"] < within for r in per_seed)
    passed = solved >= REQUIRED_SEEDS if len(per_seed) >= JUDGED_SEEDS and budget >= within else None
    return {"solved": solved, "seeds": len(per_seed), "passed": passed}


def merge(previous: dict[str, Any], fresh: dict[str, Any]) -> dict[str, Any]:
    """The examples of ``previous`` results, those run now (``fresh``) replaced; in the order of EXAMPLES."""
    envs = {**previous.get("envs", {}), **fresh}
    return {"envs": {name: envs[name] for name in sorted(envs, key=_example_order)}}


def _example_order(name: str) -> tuple[int, str]:
    """Where an example's results go: the order of EXAMPLES, any other after them by name."""
    return (EXAMPLES.index(name) if name in EXAMPLES else len(EXAMPLES), name)


def table(results: dict[str, Any]) -> str:
    """The markdown section of ``docs/benchmarks.md`` for the merged ``results``."""
    lines = [
        "## Examples of envs that are not ours: learning from scratch (issue 20)",
        "",
        f"PILCO with the default learner (moment matching, L-BFGS) on each shipped example, `python -m qtl "
        f"task=<name>`. Required: success within {REQUIRED_EPISODES} episodes (the random one included) in at "
        f"least {REQUIRED_SEEDS} of {JUDGED_SEEDS} seeds. Episode 0 is the random one; lengths are in learner "
        "steps (an episode ends early where the env terminates); learning time is model fitting plus policy "
        "search over the whole run; the env's own return (its reward, summed) is logged only. Results: "
        "`docs/bench/envs.json`.",
    ]
    for name, env in results["envs"].items():
        v, m = env["verdict"], env["machine"]
        status = {True: "met", False: "NOT met", None: "not judged: a partial run (fewer seeds or episodes)"}[
            v["passed"]]
        lines += [
            "",
            f"### {name}",
            "",
            f"`{env['command']}` at commit {env['commit']} — {env['date']}, {m['cpu']} ({m['cores']} cores), "
            f"{env['jobs']} run(s) in parallel with {env['threads']} torch thread(s) each, torch {m['torch']}; "
            f"overrides: `{' '.join(env['overrides']) or 'none'}`; {env['episodes_per_run']} episodes per seed.",
            f"Success test: {env['success_test']} ({MEANINGS.get(name, 'see its task file')}).",
            "",
            f"**Required: success within {env['within']} episodes in at least {REQUIRED_SEEDS} of {JUDGED_SEEDS} "
            f"seeds — {status} ({v['solved']} of {v['seeds']} seeds succeeded).**",
            "",
            markdown_table([[r["seed"], "—" if r["first_success"] is None else r["first_success"],
                             " ".join(f"{x:.1f}" for x in r["returns"]), " ".join(str(n) for n in r["lengths"]),
                             f"{r['env_returns'][-1]:.1f}", f"{r['learning_s']:.0f}",
                             f"{r['wall_s']:.0f}" if r["wall_s"] else "reused"] for r in env["per_seed"]],
                           ["seed", "first success (episode)", "returns per episode", "lengths",
                            "env's own return, last episode", "learning (s)", "wall (s, that call)"], "rrllrrr"),
        ]
    return "\n".join(lines)


def main() -> None:
    """Run every example and seed (reusing or resuming runs), merge with the stored results, write the section."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", nargs="+", default=list(EXAMPLES), choices=EXAMPLES)
    add_learning_arguments(parser, seeds=[0, 1, 2], within=REQUIRED_EPISODES, runs_dir=ROOT / "runs" / "bench_envs")
    args, overrides = parse_with_overrides(parser)
    if args.episodes is None:
        args.episodes = args.within - 1
    if "inverted_pendulum" in args.envs and importlib.util.find_spec("mujoco") is None:
        parser.error("task=inverted_pendulum needs the mujoco extra (pip install -e .[mujoco], or "
                     "bash scripts/setup.sh --mujoco); or leave it out: --envs pendulum mountaincar_continuous")
    budget = args.episodes + 1

    def run(job: tuple[str, int]) -> dict[str, Any]:
        name, seed = job
        run_dir = args.runs_dir / name / f"seed_{seed}"
        result = run_seed(seed, args.episodes, run_dir, [f"task={name}", *overrides], args.threads)
        return {"env": name, **result, **describe_run(run_dir, budget)}

    jobs = [(name, seed) for name in args.envs for seed in args.seeds]
    done = run_all(run, jobs, args.jobs)

    measured_on, fresh = machine(), {}
    for name in args.envs:
        per_seed = [{k: v for k, v in r.items() if k != "env"} for r in done if r["env"] == name]
        fresh[name] = {
            "date": today(), "commit": commit(), "command": command_line(), "machine": measured_on,
            "overrides": overrides, "jobs": args.jobs, "threads": args.threads,
            "within": args.within, "episodes_per_run": budget, "success_test": per_seed[0]["success_test"],
            "verdict": verdict(per_seed, args.within, budget), "per_seed": per_seed,
        }
    previous = json.loads(RESULTS.read_text()) if RESULTS.exists() else {}
    results = merge(previous, fresh)
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(results, indent=2) + "\n")
    section = table(results)
    write_section(SECTION, section)
    print(section)


if __name__ == "__main__":
    main()
