"""What the paper's experiments cost at full scale on this machine: a bound per sweep, from measured pieces.

For each stage of each experiment preset (``experiment=<name>_source`` and ``experiment=<name>``): the runs its
Hydra sweep makes (the product of its sweeper's values), the learned episodes per run and the horizon H from the
composed config; then, measured here on the task's own transitions (collected as ``bench_policy_search.py``
collects them), the model the loop fits once the data pass ``model.sparse_above`` (the SGPR with
``model.inducing`` inputs, fitted cold as the loop's ``Parts.fit_dynamics`` fits it) and one round of the
policy search: one rollout + gradient of the optimizer's R restarts at once (``optimizer.batched``), the median
of ``--repeats`` after a warm-up. Above the threshold a round's cost no longer grows with n, and below it a
round is cheaper (the exact GP's n² sums), so ``rounds x round`` bounds every search, where rounds is the
optimizer's ``max_iter`` (L-BFGS: function evaluations per restart, one batched round each). The sweep's bound
is ``runs x episodes x max_iter x round`` on one core (model fits, which warm-start, not counted); searches that
stop early cost less. The learned episodes already in each sweep's run directories (``metrics.csv`` under
``sweep.root``, the preset's or ``--experiments-root``/<name>) are counted, and the bound of what remains is
given too.

    .venv/bin/python scripts/bench_scale.py [--experiments cartpole mountaincar aircraft] [--threads 1]
        [--repeats 3] [--seed 0] [--experiments-root DIR] [--output PATH] [--tag NAME] [--no-docs] [override ...]

``--tag`` names a variant's own JSON (``scale-<tag>.json``) and section, e.g. the bound under kinematic moment
matching: ``--tag kinematic --experiments aircraft propagation.integration=speed``.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
from pathlib import Path
from typing import Any

import torch
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import DictConfig

from qtl.bench import (
    ROOT,
    command_line,
    commit,
    display_path,
    machine,
    markdown_table,
    model_label,
    parse_with_overrides,
    peak_rss_mib,
    today,
    write_results,
    write_section,
)
from qtl.bench.scale import compose_stage, model_facts, stage_model
from qtl.bench.search import batched_rollout_grad

EXPERIMENTS = ("cartpole", "mountaincar", "aircraft")
STAGES = (("source", "_source"), ("target", ""))
SECTION = "bench_scale"
DEFAULT_OUTPUT = ROOT / "docs" / "bench" / "scale.json"


def sweep_runs(cfg: DictConfig) -> int:
    """How many runs the stage's multirun makes: the product of its sweeper's value counts."""
    params = cfg.hydra.sweeper.get("params") or {}
    parsed = OverridesParser.create().parse_overrides([f"{key}={value}" for key, value in params.items()])
    return math.prod(len(list(o.sweep_string_iterator())) if o.is_sweep_override() else 1 for o in parsed)


def episodes_done(stage_dir: Path, episodes: int) -> int:
    """Learned episodes already logged under a stage's run directories (each run's counted up to ``episodes``)."""
    done = 0
    for metrics in stage_dir.rglob("metrics.csv"):
        with metrics.open() as f:
            learned = sum(1 for row in csv.DictReader(f) if int(row["episode"]) >= 1)
        done += min(learned, episodes)
    return done


def measure_task(cfg: DictConfig, repeats: int, seed: int) -> dict[str, Any]:
    """The model past the sparse threshold (fit time) and one batched search round through it."""
    parts, model, n, fit_s = stage_model(cfg, seed)
    task = parts.task
    policy = parts.initial_policy()
    round_ = batched_rollout_grad(parts, model, policy, seed, repeats)
    return {"task": task.name, "state_dim": task.state_dim, "action_dim": task.action_dim, "horizon": task.horizon,
            "n": n, **model_facts(model), "fit_s": fit_s,
            "fit_restarts": int(cfg.model.restarts), "round_s": round_["batched_rollout_grad_s_median"],
            "restarts": round_["batched_restarts"], "peak_rss_mib": peak_rss_mib()}


def stage_row(experiment: str, stage: str, cfg: DictConfig, task: dict[str, Any]) -> dict[str, Any]:
    """One stage's counts and bounds from its config and its task's measurement."""
    runs, episodes, rounds = sweep_runs(cfg), int(cfg.episodes), int(cfg.optimizer.max_iter)
    search_bound_s = rounds * task["round_s"]
    done = episodes_done(Path(cfg.sweep.root) / stage, episodes)
    return {"experiment": experiment, "stage": stage, "task": task["task"], "runs": runs, "episodes": episodes,
            "rounds_max": rounds, "search_bound_s": search_bound_s,
            "sweep_bound_core_h": runs * episodes * search_bound_s / 3600, "sweep_root": str(cfg.sweep.root),
            "episodes_done": done, "remaining_bound_core_h": (runs * episodes - done) * search_bound_s / 3600}


def markdown(tasks: list[dict[str, Any]], rows: list[dict[str, Any]], info: dict[str, Any]) -> str:
    """The section of docs/benchmarks.md."""
    lines = [
        (f"## The paper at full scale, {info['tag']} (`{' '.join(info['overrides'])}`): what each sweep costs here"
         if info.get("tag") else "## The paper at full scale: what each sweep costs here (issue 23)"),
        "",
        f"`{info['command']}` at commit {info['commit']} — {info['date']}, {info['machine']['cpu']} "
        f"({info['machine']['cores']} cores), {info['threads']} torch thread(s), torch {info['machine']['torch']}; "
        f"1-min load average {info['load_before']:.2f} before, {info['load_after']:.2f} after. "
        f"Results: `{info['output']}`.",
        "",
        "Measured per task, on its own transitions just past `model.sparse_above` (the full-scale presets' "
        "sparse GP, fitted cold with the preset's restarts): the fit, and one policy-search round (rollout + "
        "gradient of the optimizer's R restarts at once, median of the repeats after a warm-up).",
        "",
        markdown_table([[t["task"], f"{t['state_dim']}, {t['action_dim']}", t["horizon"], t["n"], model_label(t),
                         f"{t['fit_s']:.1f}", f"{t['round_s']:.2f} (R = {t['restarts']})"] for t in tasks],
                       ["task", "state, action dims", "H", "n", "model", "fit (s)", "one round, R restarts (s)"],
                       "llrrlrr"),
    ]
    lines += [
        "",
        "The bound of each sweep on one core: runs × learned episodes × `optimizer.max_iter` rounds × one round "
        "(each restart's evaluation budget, which a line search in progress may pass by a few; a search that stops "
        "early costs less; model fits not counted). Done: the learned episodes already in "
        "the sweep's run directories (`sweep.root`, in the last column).",
        "",
        markdown_table([[r["experiment"], r["stage"], r["task"], r["runs"], r["episodes"], r["rounds_max"],
                         f"{r['search_bound_s'] / 60:.1f}", f"{r['sweep_bound_core_h']:.1f}",
                         f"{r['episodes_done']} of {r['runs'] * r['episodes']}", f"{r['remaining_bound_core_h']:.1f}",
                         f"`{r['sweep_root']}`"] for r in rows],
                       ["experiment", "stage", "task", "runs", "learned episodes", "rounds ≤", "search ≤ (min/episode)",
                        "sweep ≤ (core-h)", "done (episodes)", "remaining ≤ (core-h)", "sweep.root"], "lllrrrrrrrl"),
    ]
    total = sum(r["sweep_bound_core_h"] for r in rows)
    left = sum(r["remaining_bound_core_h"] for r in rows)
    lines += ["", f"All stages: ≤ {total:.0f} core-hours of policy search, ≤ {left:.0f} of them still to run."]
    return "\n".join(lines) + "\n"


def main() -> None:
    """Measure each task once, bound each stage's sweep; write the JSON and (unless ``--no-docs``) the section."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--experiments", nargs="+", choices=EXPERIMENTS, default=list(EXPERIMENTS))
    parser.add_argument("--threads", type=int, default=1, help="torch threads (a sweep job uses one)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0, help="of the data collection and the fit")
    parser.add_argument("--experiments-root", type=Path, default=None,
                        help="each experiment's sweep.root is DIR/<name> (default: the preset's)")
    parser.add_argument("--output", type=Path, help="the JSON (default: docs/bench/scale[-<tag>].json)")
    parser.add_argument("--tag", default="", help="a variant's name: its own JSON and section (e.g. 'kinematic')")
    parser.add_argument("--no-docs", action="store_true")
    args, overrides = parse_with_overrides(parser)
    if any(o.split("=", 1)[0].lstrip("+~") == "sweep.root" for o in overrides):
        parser.error("sweep.root would be shared by every experiment: give --experiments-root DIR (DIR/<name> each)")
    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()[0]
    measured: dict[str, dict[str, Any]] = {}
    rows = []
    for experiment in args.experiments:
        for stage, suffix in STAGES:
            root = [] if args.experiments_root is None else [f"sweep.root={args.experiments_root / experiment}"]
            cfg = compose_stage(experiment + suffix, [*overrides, *root])
            name = str(cfg.task.name)
            if name not in measured:
                measured[name] = measure_task(cfg, args.repeats, args.seed)
                print(json.dumps(measured[name]), file=sys.stderr, flush=True)
            rows.append(stage_row(experiment, stage, cfg, measured[name]))
    suffix = f"-{args.tag}" if args.tag else ""
    output = (args.output or DEFAULT_OUTPUT.with_stem(DEFAULT_OUTPUT.stem + suffix)).resolve()
    info = {"date": today(), "command": command_line(), "commit": commit(), "tag": args.tag,
            "machine": machine(), "threads": args.threads, "repeats": args.repeats, "seed": args.seed,
            "overrides": overrides, "load_before": load_before, "load_after": os.getloadavg()[0],
            "output": display_path(output)}
    write_results(output, {**info, "tasks": list(measured.values())}, rows)
    section = markdown(list(measured.values()), rows, info)
    if not args.no_docs:
        write_section(SECTION + suffix, section)
    print(section)


if __name__ == "__main__":
    main()
