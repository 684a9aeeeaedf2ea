"""Benchmark — issue 64's state constraints: the cart-pole on a ±0.7 m track, learned with and without its constraint.

``task=cartpole_track`` (the env terminates once |x| > 0.7 m) is learned twice per seed through the real CLI: with
its ``terminate`` constraint on x, and with the constraints switched off (``task.constraints=[]``; the env still
terminates, the learner is not told). One table reports per arm how many seeds succeed within ``--within`` episodes
(the random one included), each seed's first success, the episodes whose real states left the declared bound
(counted against the task's bounds in both arms, from the runs' checkpoints: ``qtl.bench.constraints``) and the
policy search's seconds per evaluation of the predicted return. Required: with the constraint, success within 10
episodes in at least 4 of 5 seeds, and fewer crossings than without. Writes ``docs/bench/constraints[-<tag>].json``
and (unless ``--no-docs``) its section of ``docs/benchmarks.md``; extra arguments are Hydra overrides for every run
of both arms. A finished run is reused and an interrupted one resumed (``qtl.launch``), so the benchmark can be
completed over several calls.

    python scripts/bench_constraints.py [--seeds 0 1 2 3 4] [--within 10] [--jobs 2] [--threads 1] [--tag NAME]
        [--runs-dir DIR] [--no-docs] [--track-limit METRES] [override ...]

The figure of record starts from three random episodes (``random_episodes=3``; ``--episodes`` then defaults to 7, so
10 in all): ``python scripts/bench_constraints.py random_episodes=3``.
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics

import torch
from hydra.errors import HydraException

from qtl.bench import (
    ROOT,
    add_learning_arguments,
    command_line,
    commit,
    first_successes,
    initial_episodes,
    machine,
    markdown_table,
    mean_std,
    parse_with_overrides,
    run_all,
    run_seed,
    today,
    write_results,
    write_section,
)
from qtl.bench.constraints import constraint_figures, declared_bounds, same_model_cost
from qtl.errors import UserError

TASK = "cartpole_track"
# The two arms, in the table's order: their overrides after task=cartpole_track.
ARMS: dict[str, list[str]] = {"without": ["task.constraints=[]"], "with": []}


def track_arms(limit: float | None) -> dict[str, list[str]]:
    """The arms' overrides on a track of ±``limit`` m (the env's limit and the declared bound; None: the task's own)."""
    if limit is None:
        return ARMS
    track = f"task.env.track_limit={limit:g}"
    bound = f"task.constraints=[{{dim:0,low:{-limit:g},high:{limit:g},kind:terminate}}]"
    return {"without": [track, "task.constraints=[]"], "with": [track, bound]}

ARM_LABELS = {"without": "none (`task.constraints=[]`)", "with": "`terminate` on x"}
REQUIRED_EPISODES = 10  # success within this many episodes, the random one included (--within)
REQUIRED_SEEDS = 4  # in at least this many of ...
JUDGED_SEEDS = 5  # ... this many seeds (of each arm); fewer make a partial run that is not judged


def arm_summary(results: list[dict], within: int) -> dict:
    """One arm's per-seed results summed up: seeds that succeeded in time, crossings, search cost."""
    solved = [r["seed"] for r in results if r["first_success"] is not None and r["first_success"] < within]
    costs = [r["search_s_per_evaluation"] for r in results if r["search_s_per_evaluation"] is not None]
    return {
        "seeds": len(results),
        "solved": len(solved),
        "crossings": sum(r["crossings"] for r in results),
        "episodes": sum(len(r["crossed"]) for r in results),
        "search_s_per_evaluation": statistics.mean(costs) if costs else None,
    }


def verdict(summaries: dict[str, dict]) -> bool | None:
    """The requirement: with the constraint ≥ 4 of 5 seeds succeed in time and cross less often than without.

    None (not judged) unless both arms have at least 5 seeds.
    """
    if any(summaries[arm]["seeds"] < JUDGED_SEEDS for arm in ARMS):
        return None
    on, off = summaries["with"], summaries["without"]
    return on["solved"] >= REQUIRED_SEEDS and on["crossings"] < off["crossings"]


def results_table(results: list[dict], summaries: dict[str, dict], within: int) -> str:
    """The markdown table: one row per arm (seeds in order within each cell)."""
    rows = []
    for arm in ARMS:
        per_seed = sorted((r for r in results if r["arm"] == arm), key=lambda r: r["seed"])
        summary = summaries[arm]
        costs = [1e3 * r["search_s_per_evaluation"] for r in per_seed if r["search_s_per_evaluation"] is not None]
        rows.append([
            ARM_LABELS[arm],
            f"{summary['solved']} of {summary['seeds']}",
            first_successes(per_seed),
            f"{summary['crossings']} of {summary['episodes']} ({' '.join(str(r['crossings']) for r in per_seed)})",
            mean_std(costs),
            mean_std([r["policy_search_s_per_episode"] for r in per_seed]),
        ])
    return markdown_table(rows, ["constraints", f"success within {within} episodes",
                                 "first success per seed (episode, 0 = random)",
                                 "episodes that crossed the bound (per seed)", "search ms per evaluation",
                                 "policy search s per episode"], "lrlrrr")


def section(info: dict, results: list[dict]) -> str:
    """The section of ``docs/benchmarks.md``: command, date, machine, verdict and the table."""
    m, within, summaries = info["machine"], info["within"], info["summaries"]
    on, off = summaries["with"], summaries["without"]
    state = {True: "met", False: "NOT met", None: "not judged: a partial run of fewer seeds"}[info["passed"]]
    bounds = ", ".join(f"x[{b['dim']}] in [{b['low']}, {b['high']}]" for b in info["bounds"]) or "none"
    tag = f" ({info['tag']})" if info["tag"] else ""
    random = info.get("random_episodes", 1)
    limit = info.get("track_limit") or info["bounds"][0]["high"]  # the task's own bound unless --track-limit
    return "\n".join([
        f"## State constraints: the cart-pole on a ±{limit:g} m track{tag}",
        "",
        f"`{info['command']}` at commit {info['commit']} — {info['date']}, {m['cpu']} ({m['cores']} cores), "
        f"{info['jobs']} run(s) in parallel with {info['threads']} torch thread(s) each, torch {m['torch']}. "
        f"`task={TASK}`, {info['episodes_per_run']} episodes per seed ({random} random + "
        f"{info['episodes_per_run'] - random} learned), once with its `terminate` constraint and once with "
        f"`task.constraints=[]` (the env terminates in both). Crossings: episodes whose real states left {bounds}. "
        f"Search cost: policy-search seconds over evaluations of the predicted return, learned episodes. "
        f"Results: `{info['results_file']}`.",
        "",
        f"**Required: with the constraint, success within {within} episodes in at least {REQUIRED_SEEDS} of "
        f"{JUDGED_SEEDS} seeds, and fewer crossings than without — {state} ({on['solved']} of {on['seeds']} seeds; "
        f"{on['crossings']} crossings with, {off['crossings']} without).**",
        "",
        results_table(results, summaries, within),
        *(["", cost_line(info["same_model_cost"])] if info.get("same_model_cost") else []),
    ])


def cost_line(cost: dict) -> str:
    """The constraints' own cost: one rollout + gradient with and without them on the same model and ψ."""
    return (f"The runs' search costs differ by their data (an arm whose episodes end early fits a smaller GP). On the "
            f"same model and ψ (the `with` arm's seed {cost['seed']} after its episode {cost['episode']}, n = "
            f"{cost['n']}), one rollout + gradient takes {1e3 * cost['with_s']:.1f} ms with the constraint and "
            f"{1e3 * cost['without_s']:.1f} ms without (median of {cost['repeats']}, alternating; ratio "
            f"{cost['with_s'] / cost['without_s']:.2f}).")


def main() -> None:
    """Run both arms for every seed (reusing or resuming runs), judge the requirement, write the JSON and section."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_learning_arguments(parser, seeds=[0, 1, 2, 3, 4], within=REQUIRED_EPISODES,
                           runs_dir=ROOT / "runs" / "bench_constraints")
    parser.add_argument("--tag", default="", help="names the result files and table")
    parser.add_argument("--no-docs", action="store_true", help="write the JSON only, not docs/benchmarks.md")
    parser.add_argument("--track-limit", type=float, default=None,
                        help="a track of ±this many metres instead of the task's (env limit and declared bound)")
    args, overrides = parse_with_overrides(parser)
    if args.within < 1 or min(args.seeds) < 0 or args.jobs < 1 or args.threads < 1:
        parser.error("--within, --jobs and --threads must be >= 1 and --seeds >= 0")
    random = initial_episodes(overrides)  # random_episodes=N among the overrides, else 1
    if args.episodes is None:
        args.episodes = args.within - random
    if args.episodes < 1:
        parser.error(f"--episodes must be >= 1, got {args.episodes}")
    if args.track_limit is not None and not args.track_limit > 0:
        parser.error(f"--track-limit must be > 0 (metres), got {args.track_limit}")
    arms = track_arms(args.track_limit)

    # Both arms count crossings against the bounds the task declares (the arm without them declares none).
    try:
        bounds = declared_bounds([f"task={TASK}", *arms["with"], *overrides])
    except (HydraException, UserError) as err:
        parser.error(str(err).strip().splitlines()[0])
    if not bounds:
        parser.error(f"task={TASK} with {overrides} declares no constraints: nothing to compare")
    name = "constraints" + (f"-{args.tag}" if args.tag else "")
    runs_dir = args.runs_dir / name

    def one(item: tuple[str, int]) -> dict:
        arm, seed = item
        run_dir = runs_dir / arm / f"seed_{seed}"
        result = run_seed(seed, args.episodes, run_dir, [f"task={TASK}", *arms[arm], *overrides], args.threads)
        return {"arm": arm, **result, **constraint_figures(run_dir, random + args.episodes, bounds)}

    results = run_all(one, [(arm, seed) for arm in arms for seed in args.seeds], args.jobs)
    torch.set_num_threads(args.threads)  # as the runs searched
    cost = same_model_cost(runs_dir / "with" / f"seed_{args.seeds[0]}") | {"seed": args.seeds[0]}
    summaries = {arm: arm_summary([r for r in results if r["arm"] == arm], args.within) for arm in arms}
    out = ROOT / "docs" / "bench" / f"{name}.json"
    info = {"date": today(), "commit": commit(), "command": command_line(), "machine": machine(),
            "task": TASK, "overrides": overrides, "arms": arms, "tag": args.tag, "within": args.within,
            "track_limit": args.track_limit, "episodes_per_run": random + args.episodes, "random_episodes": random,
            "jobs": args.jobs, "threads": args.threads,
            "bounds": [dataclasses.asdict(b) for b in bounds], "results_file": out.relative_to(ROOT).as_posix(),
            "required": f"with constraints: success within {args.within} episodes in >= {REQUIRED_SEEDS} of "
                        f"{JUDGED_SEEDS} seeds, and fewer crossings than without",
            "summaries": summaries, "passed": verdict(summaries), "same_model_cost": cost}
    write_results(out, info, results)
    text = section(info, results)
    if not args.no_docs:
        write_section(f"bench_{name}", text)
    print(text)


if __name__ == "__main__":
    main()
