"""Benchmark — the acceptance figure of the learning loop: PILCO learns the 0.5 kg cart-pole swing-up.

Runs the real CLI (``python -m qtl``) once per seed, in parallel processes of one torch thread
each, and reports per seed the first successful episode (the task's criterion: the pendulum tip
within 0.15 m of the upright target for the last 2 s), the learning curve and the wall time per
episode split into model fitting and policy search. Required: success within 8 episodes (the
random one included) in at least 4 of 5 seeds. Writes ``docs/bench/cartpole[-<tag>].json`` and
its table in ``docs/benchmarks.md``; extra arguments are Hydra overrides for every run. A finished
run directory made by the same overrides is reused and an interrupted one resumed (``qtl.launch``),
so a long benchmark can be completed over several calls.

    python scripts/bench_cartpole.py [--seeds 0 1 2 3 4] [--within 8] [--jobs 2] [--threads 1] [--tag NAME]
        [override ...]
    python scripts/bench_cartpole.py --within 10 --tag particles propagation=particles
"""

from __future__ import annotations

import argparse
import json

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

REQUIRED_EPISODES = 8  # success within this many episodes, the random one included (--within)
REQUIRED_SEEDS = 4  # in at least this many of ...
JUDGED_SEEDS = 5  # ... this many seeds; fewer seeds make a partial run that is not judged


def main() -> None:
    """Run every seed (reusing or resuming runs), judge the requirement, write the JSON and the section."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_learning_arguments(parser, seeds=[0, 1, 2, 3, 4], within=REQUIRED_EPISODES,
                           runs_dir=ROOT / "runs" / "bench_cartpole")
    parser.add_argument("--tag", default="", help="names the result files and table (e.g. 'particles')")
    args, overrides = parse_with_overrides(parser)
    if args.episodes is None:
        args.episodes = args.within - 1

    name = "cartpole" + (f"-{args.tag}" if args.tag else "")
    runs_dir = args.runs_dir / name
    results = run_all(lambda s: run_seed(s, args.episodes, runs_dir / f"seed_{s}", overrides, args.threads),
                      args.seeds, args.jobs)
    solved = [r for r in results if r["first_success"] is not None and r["first_success"] < args.within]
    passed = len(solved) >= REQUIRED_SEEDS if len(results) >= JUDGED_SEEDS else None

    info = {"date": today(), "commit": commit(), "command": command_line(), "machine": machine(),
            "overrides": overrides, "episodes_per_run": args.episodes + 1, "jobs": args.jobs, "threads": args.threads,
            "required": f"success within {args.within} episodes in >= {REQUIRED_SEEDS} of {JUDGED_SEEDS} seeds",
            "passed": passed, "results": results}
    out = ROOT / "docs" / "bench" / f"{name}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(info, indent=2) + "\n")

    m = info["machine"]
    lines = [
        f"## Cart-pole swing-up, 0.5 kg, from scratch{f' ({args.tag})' if args.tag else ''}",
        "",
        f"`{info['command']}` at commit {info['commit']} — "
        f"{info['date']}, {m['cpu']} ({m['cores']} cores), {args.jobs} run(s) in parallel with "
        f"{args.threads} torch thread(s) each, torch {m['torch']}. {args.episodes + 1} episodes per seed (1 random + "
        f"{args.episodes} learned). Success: tip within 0.15 m of the target for the last 2 s. "
        f"Results: `docs/bench/{name}.json`.",
        "",
        f"**Required: success within {args.within} episodes in at least {REQUIRED_SEEDS} of {JUDGED_SEEDS} seeds — "
        + ({True: "met", False: "NOT met", None: "not judged: a partial run of fewer seeds"}[passed])
        + f" ({len(solved)} of {len(results)} seeds succeeded).**",
        "",
        markdown_table([[r["seed"], "—" if r["first_success"] is None else r["first_success"],
                         " ".join(f"{v:.1f}" for v in r["returns"]), f"{r['model_fit_s_per_episode']:.1f}",
                         f"{r['policy_search_s_per_episode']:.1f}", f"{r['wall_s']:.0f}" if r["wall_s"] else "reused"]
                        for r in results],
                       ["seed", "first success (episode, 0 = random)", "returns per episode", "model fit (s/episode)",
                        "policy search (s/episode)", "wall (s, this call)"], "rrlrrr"),
    ]
    write_section(f"bench_{name}", "\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
