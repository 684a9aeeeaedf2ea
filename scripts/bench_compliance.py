"""Benchmark — task compliance Λ (Eq. 14) per target, and the transfer gate that acts on it (issue 21).

**Λ** (always): per family and seed, the source run of that seed and the target's initial episode
exactly as the loop runs it for a θ-only transfer (random actions; action and env seeds derived from
the run seed), then Λ of those tuples, i.e. the value the compliance gate reads at the first model:

- ``kernel``: :func:`~qtl.transfer.compliance.kernel_compliance` with Scott's bandwidth (the gate's);
- ``kernel, no bandwidth``: the source GP's predictive alone;
- ``likelihood ratio``: :func:`~qtl.transfer.compliance.task_compliance`, the target GP fitted as the
  loop fits its first model.

Beside them, per target, the median over tuples (and seeds) of the largest per-output distance
|Δ − μ| of a tuple in predictive standard deviations √v and in bandwidths h: why the exact densities
saturate on our near-deterministic simulators.

**Learning** (``--learn``, mountain car by default): per target and seed, PILCO, the θ-only transfer
(``approach`` with ``transfer.policy=false``), the approach as its preset (arm ``qtl``: θ_s and ψ_s for
QTL-PILCO, the paper's Table 4 runs) and the θ-only transfer with the gate
``transfer.min_compliance=<--gate>``, each through the real CLI (``qtl.launch.ensure_run``: a finished run
made by the same overrides is reused, an interrupted one resumed). The gate value is one per family,
passed on the command line, chosen from the Λ table before these runs; ``--gate-on far`` runs the gated arm on
the far targets only (a near target whose Λ at the first model is above the gate repeats its ungated run exactly:
the gate reads the first model only, and runs are deterministic). Reported: first success per
seed, AUC, final performance, Λ at the first model and the episode where a gated run fell back.

**Exploration** (``--explore KEY=VALUE ...``, on its own): PILCO and θ-only transfer on other targets of
the family, any env argument (a changed friction, a weaker actuator, a longer pole), in the search for a
target where transfer hurts; their own table.

Writes ``docs/bench/compliance.json`` and its sections of ``docs/benchmarks.md``.

    python scripts/bench_compliance.py [--families mountaincar cartpole] [--seeds 0 1 2 3 4]
    python scripts/bench_compliance.py --families mountaincar --learn --gate 0.5 --episodes 10 --jobs 2
    python scripts/bench_compliance.py --families cartpole --explore friction=5.0 max_force=5.0 --seeds 0 1
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import statistics
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_module

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
from qtl.build import build
from qtl.checkpoint import CHECKPOINT_DIR, load_checkpoint
from qtl.config import register_configs
from qtl.data import TransitionDataset
from qtl.episodes import random_actor, run_episode
from qtl.launch import ensure_run
from qtl.metrics import Curve
from qtl.report import SOURCE_DIR, TARGET_DIR, discover, plot_learning_curves
from qtl.seeding import ACTION_STREAM, ENV_STREAM, MODEL_STREAM, derive_seed, torch_generator
from qtl.transfer.compliance import kernel_compliance, task_compliance
from qtl.transfer.source import SourceRun


@dataclass(frozen=True)
class Family:
    """A source task and its targets along one env parameter (``task.env.<axis>``)."""

    task: str
    axis: str
    unit: str
    source_value: float
    near: tuple[float, ...]
    far: tuple[float, ...]
    sources: Path  # seed_<k> run directories of the source task

    def label(self, value: float) -> str:
        """A target's name in tables: '300 %' or '2.0 kg'."""
        return f"{value * 100:g} %" if self.unit == "%" else f"{value:.1f} {self.unit}"


FAMILIES = {
    "mountaincar": Family("mountaincar", "power", "%", 1.0, (0.5, 1.5), (3.0,),
                          ROOT / "runs" / "experiments" / "mountaincar" / "source"),
    "cartpole": Family("cartpole", "pole_mass", "kg", 0.5, (0.8, 1.0, 1.5, 2.0), (5.0,),
                       ROOT / "runs" / "bench_cartpole" / "cartpole-fast"),
}
ARMS = ("pilco", "transfer", "qtl", "gated")  # the learning runs per target and seed
EXPLORE_ARMS = ("pilco", "transfer")  # the runs per extra target of --explore (and "gated" with --gate)
# What --explore-arms may choose: also QTL-PILCO (θ_s and ψ_s) and QTL-PILCO gated.
EXPLORE_CHOICES = ("pilco", "transfer", "qtl", "gated", "gated_qtl")
LEARNING_COLUMNS = ["target", "arm", "first success per seed", "solved", "AUC", "final", "Λ at the first model",
                    "fell back after episode"]
LEARNING_ALIGN = "lllrrrrl"
EXPLORE_ARM_HELP = {  # how each arm's table describes it
    "pilco": "pilco: PILCO",
    "transfer": "transfer: θ-only transfer (`approach={approach} transfer.policy=false`, random initial episode)",
    "gated": "gated: the same with `transfer.min_compliance={gate}`",
    "qtl": "qtl: `approach={approach}` as its preset (θ_s and ψ_s, initial episode run by ψ_s)",
    "gated_qtl": "gated_qtl: qtl with `transfer.min_compliance={gate}`",
}


def arm_overrides(approach: str, gate: float | None) -> dict[str, list[str]]:
    """Each arm's Hydra overrides (the source's path apart): PILCO, θ-only transfer, QTL-PILCO and their gated forms."""
    transfer = [f"approach={approach}", "transfer.policy=false", "transfer.compliance=kernel"]
    qtl = [f"approach={approach}", "transfer.compliance=kernel"]
    gate_overrides = [] if gate is None else [f"transfer.min_compliance={gate}"]
    return {"pilco": [], "transfer": transfer, "gated": [*transfer, *gate_overrides], "qtl": qtl,
            "gated_qtl": [*qtl, *gate_overrides]}


def target_config(family: Family, value: float, seed: int, extra: list[str] | None = None):
    """The composed ``train`` config of a target run (what ``qtl-train`` would run)."""
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        return compose(config_name="train", overrides=[f"task={family.task}", f"task.env.{family.axis}={value}",
                                                       f"seed={seed}", *(extra or [])])


def initial_compliance(family: Family, value: float, seed: int, extra: list[str] | None = None) -> dict:
    """Λ of the target's initial (random) episode under the seed's source, three ways, and the tuples' distances.

    Also ``kernel_source_policy``: Λ (kernel) of the initial episode run by ψ_s instead, what the gate of a run
    that transfers ψ_s (the ``qtl`` arm) reads at its first model.
    ``extra``: Hydra overrides of the target runs (as ``--learn`` passes them), so that the episode is theirs.
    """
    cfg = target_config(family, value, seed, extra)
    parts = build(cfg)
    source = SourceRun.load(family.sources / f"seed_{seed}")
    source.check_compatible(parts.task)
    rng = np.random.default_rng(derive_seed(seed, 0, ACTION_STREAM))  # as the loop's episode 0
    episode = run_episode(parts.task.make_env(), parts.task, random_actor(parts.task, rng),
                          derive_seed(seed, 0, ENV_STREAM))
    data = TransitionDataset(parts.task.state_dim, parts.task.action_dim, parts.task.angle_dims)
    data.add_episode(episode.states, episode.actions)
    target = parts.fit_dynamics(data, torch_generator(seed, 1, MODEL_STREAM))  # the loop's first model
    source_model = source.model(parts.features)
    kernel = kernel_compliance(source_model, target)
    policy = parts.initial_policy()  # ψ_s in it, as a run with transfer.policy=true starts
    source.check_policy(policy)
    policy.load_state_dict(source.policy)
    by_psi_s = run_episode(parts.task.make_env(), parts.task, parts.actor(policy), derive_seed(seed, 0, ENV_STREAM))
    psi_data = TransitionDataset(parts.task.state_dim, parts.task.action_dim, parts.task.angle_dims)
    psi_data.add_episode(by_psi_s.states, by_psi_s.actions)
    psi_target = parts.fit_dynamics(psi_data, torch_generator(seed, 1, MODEL_STREAM))
    mean, var = source_model.predict(target.train_x, include_noise=True)
    error = (target.train_y - mean).abs()  # n x E
    return {
        "seed": seed, "value": value, "tuples": len(data), "source_tuples": len(source.dataset),
        "source_episode": source.episode,
        "kernel": kernel.value,
        "kernel_no_bandwidth": kernel_compliance(source_model, target, bandwidth="none").value,
        "likelihood_ratio": task_compliance(source_model, target).value,
        "kernel_source_policy": kernel_compliance(source_model, psi_target).value,
        "bandwidth": kernel.bandwidth.tolist(),
        "median_distance_in_predictive_sd": float((error / var.sqrt()).amax(-1).median()),
        "median_distance_in_bandwidths": float((error / kernel.bandwidth).amax(-1).median()),
    }


def compliance_verdict(family: Family, rows: dict[float, list[dict]]) -> dict[str, bool]:
    """The issue's requirements on Λ (kernel): near targets in (0.05, 0.95), ordered by the change, far lowest."""
    means = {value: statistics.mean(r["kernel"] for r in rows[value]) for value in rows}
    near = [means[v] for v in family.near]
    verdict = {"near targets not saturated (0.05 < Λ < 0.95)": all(0.05 < m < 0.95 for m in near)}
    ordered = sorted(family.near, key=lambda v: abs(v - family.source_value))
    if family.axis == "pole_mass":
        verdict["ordered by mass"] = all(means[a] > means[b] for a, b in itertools.pairwise(ordered))
    verdict["far target lowest"] = all(means[f] < min(near) for f in family.far)
    return verdict


def run_header() -> str:
    """How a section of this script names its run: the command, date, machine and commit."""
    m = machine()
    return (f"`{command_line()}` — {today()}, {m['cpu']} ({m['cores']} cores), torch {m['torch']}, "
            f"commit {commit()}.")


def compliance_section(
    family: Family, rows: dict[float, list[dict]], verdict: dict[str, bool], seeds: list[int], header: str
) -> str:
    """The Λ table of one family, markdown; ``header``: the command, date, machine and commit that made it."""
    first = rows[family.near[0]][0]
    lines = [
        f"## Task compliance: {family.task}, {family.label(family.source_value)} source",
        "",
        header,
        "",
        f"Sources: `{display_path(family.sources)}/seed_<k>` (last checkpoint: episode "
        f"{first['source_episode']} of seed {first['seed']}, m = {first['source_tuples']} tuples). Target tuples: "
        f"each target's initial random episode of the same seed ({first['tuples']} tuples), what the gate reads at "
        f"the first model. Last columns: the same from the initial episode run by the source's policy ψ_s, what the "
        f"gate of a run that transfers ψ_s (QTL-PILCO as the paper runs it) reads. Seeds "
        f"{', '.join(map(str, seeds))}; mean ± std over seeds.",
        "",
        "**Required: " + "; ".join(f"{k} — {'met' if ok else 'NOT met'}" for k, ok in verdict.items()) + ".**",
        "",
    ]
    cells = []
    for value, per_seed in rows.items():
        kind = " (far)" if value in family.far else (" (source task)" if value == family.source_value else "")
        cells.append([
            f"{family.label(value)}{kind}", mean_std([r["kernel"] for r in per_seed], 2),
            " ".join(f"{r['kernel']:.2f}" for r in per_seed), mean_std([r["kernel_no_bandwidth"] for r in per_seed], 3),
            mean_std([r["likelihood_ratio"] for r in per_seed], 3),
            f"{statistics.median(r['median_distance_in_predictive_sd'] for r in per_seed):.1f}",
            f"{statistics.median(r['median_distance_in_bandwidths'] for r in per_seed):.2f}",
            mean_std([r["kernel_source_policy"] for r in per_seed], 2),
            " ".join(f"{r['kernel_source_policy']:.2f}" for r in per_seed),
        ])
    lines.append(markdown_table(cells, [
        "target", "Λ, kernel (Scott bandwidth)", "per seed", "Λ, kernel, no bandwidth", "Λ, likelihood ratio",
        "median distance (predictive sd)", "median distance (bandwidths)", "Λ, kernel, episode by ψ_s", "per seed",
    ], "lrlrrrrrl"))
    return "\n".join(lines)


def fell_back_at(run_dir: Path) -> int | None:
    """The first episode after which a gated run had fallen back to PILCO, from its checkpoints; None if never."""
    for path in sorted((run_dir / CHECKPOINT_DIR).glob("episode_*.pt")):
        state = load_checkpoint(path).get("transfer") or {}
        if state.get("fallen_back"):
            return int(path.stem.split("_")[1])
    return None


def learning_row(target: str, arm: str, per_seed: list[dict], gated: bool) -> list[str]:
    """One row of a learning table: an arm on a target over the seeds (the fall-backs for a gated arm only)."""
    first_lambda = [r["compliance"][1] for r in per_seed if r["compliance"][1] == r["compliance"][1]]
    return [target, arm, first_successes(per_seed),
            f"{sum(r['first_success'] is not None for r in per_seed)}/{len(per_seed)}",
            mean_std([r["auc"] for r in per_seed]), mean_std([r["final_performance"] for r in per_seed]),
            mean_std(first_lambda, 2),
            " ".join("—" if r["fell_back_after"] is None else str(r["fell_back_after"]) for r in per_seed)
            if gated else ""]


def link_experiment(root: Path, sources: Path, arms: list[str]) -> None:
    """Lay ``root`` out as an experiment directory that ``qtl.report`` reads: ``target/<arm>`` and ``source`` links."""
    (root / TARGET_DIR).mkdir(parents=True, exist_ok=True)
    for arm in arms:
        link = root / TARGET_DIR / arm
        if not link.exists():
            link.symlink_to(Path("..") / arm, target_is_directory=True)
    if not (root / SOURCE_DIR).exists():
        (root / SOURCE_DIR).symlink_to(sources.resolve(), target_is_directory=True)


def learn(family: Family, args: argparse.Namespace) -> tuple[dict, str]:
    """PILCO, θ-only transfer and gated transfer on every target and seed; their table, markdown."""
    root = args.runs_dir / family.task
    values = [*family.near, *family.far]
    overrides_of = arm_overrides(args.approach, args.gate)

    def run(job: tuple[str, float, int]) -> None:
        arm, value, seed = job
        source = [f"transfer.source={family.sources / f'seed_{seed}'}"] if arm != "pilco" else []
        overrides = [f"task={family.task}", f"task.env.{family.axis}={value}", f"seed={seed}",
                     f"episodes={args.episodes}", *overrides_of[arm], *source, *args.overrides]
        ensure_run(overrides, root / arm / f"{family.axis}{value:g}" / f"seed_{seed}", args.episodes + 1)

    # PILCO and transfer first (seed-major, so that partial results pair up), then the gated runs, far targets first.
    jobs = [(arm, value, seed) for seed in args.seeds for value in values for arm in ("pilco", "transfer", "qtl")
            if arm in args.arms]
    gated = [*family.far, *(family.near if args.gate_on == "all" else ())]
    if "gated" in args.arms:
        jobs += [("gated", value, seed) for value in gated for seed in args.seeds]
    run_all(run, jobs, args.jobs)

    link_experiment(root, family.sources, args.arms)
    figure, *others = plot_learning_curves(discover(root), args.figures / f"compliance_{family.task}_learning_curves")
    for other in others:  # the png goes into the docs; the report's other formats are not needed there
        other.unlink()
    budget = args.episodes + 1
    results: dict = {}
    lines = [
        f"## Compliance gate: {family.task}, {family.label(family.source_value)} source",
        "",
        f"{run_header()} Per target and seed: PILCO; "
        f"θ-only transfer (`approach={args.approach} transfer.policy=false`, random initial episode); the same with "
        f"`transfer.min_compliance={args.gate}` (the gate, kernel compliance); arm qtl: `approach={args.approach}` as "
        f"its preset (θ_s and ψ_s, initial episode run by ψ_s). {budget} episodes per run (1 random "
        f"+ {args.episodes} learned), one torch thread each, {args.jobs} in parallel. Runs: "
        f"`{display_path(root)}`. AUC: trapezoid over the {budget} episodes; final: mean of the last 3.",
        "",
        f"![learning curves, mean ± std over seeds]({figure.relative_to(args.figures.parent)})",
        "",
    ]
    rows = []
    for value in values:
        for arm in [a for a in args.arms if a != "gated" or value in gated]:
            per_seed = []
            for seed in args.seeds:
                run_dir = root / arm / f"{family.axis}{value:g}" / f"seed_{seed}"
                curve = Curve.read(run_dir, budget)
                per_seed.append({"seed": seed, "returns": curve.returns, "successes": [int(s) for s in curve.successes],
                                 "compliance": curve.compliance, "fell_back_after": fell_back_at(run_dir),
                                 **curve.summary()})
            results.setdefault(str(value), {})[arm] = per_seed
            rows.append(learning_row(family.label(value) + (" (far)" if value in family.far else ""), arm, per_seed,
                                     gated=arm == "gated"))
    lines += [markdown_table(rows, LEARNING_COLUMNS, LEARNING_ALIGN), "",
              "Returns per episode (target, arm, seed: curve):", ""]
    for value, arms in results.items():
        for arm, per_seed in arms.items():
            for r in per_seed:
                lines.append(f"- {family.label(float(value))}, {arm}, seed {r['seed']}: "
                             + " ".join(f"{v:.1f}" for v in r["returns"]))
    return results, "\n".join(lines)


def env_override(family: Family, key: str, value: float) -> str:
    """``task.env.<key>=<value>``, with a ``+`` where the task's config does not list the key (any env kwarg)."""
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        listed = key in compose(config_name="train", overrides=[f"task={family.task}"]).task.env
    return f"{'' if listed else '+'}task.env.{key}={value:g}"


def explore(family: Family, args: argparse.Namespace) -> tuple[dict, str]:
    """PILCO and θ-only transfer (and, with ``--gate``, the gated transfer) on the targets of ``--explore``.

    Does θ_s hurt there, and does the gate catch it? Its table, markdown.
    """
    root = args.runs_dir / family.task / "explore"
    overrides_of = arm_overrides(args.approach, args.gate)
    arms = args.explore_arms or [*EXPLORE_ARMS, *(["gated"] if args.gate is not None else [])]
    env = {target: env_override(family, *target) for target in args.explore}  # composed here, not in the threads

    def run_dir(arm: str, key: str, value: float, seed: int) -> Path:
        return root / arm / f"{key}{value:g}" / f"seed_{seed}"

    def run(job: tuple[str, tuple[str, float], int]) -> None:
        arm, (key, value), seed = job
        source = [f"transfer.source={family.sources / f'seed_{seed}'}"] if arm != "pilco" else []
        overrides = [f"task={family.task}", env[key, value], f"seed={seed}",
                     f"episodes={args.episodes}", *overrides_of[arm], *source, *args.overrides]
        ensure_run(overrides, run_dir(arm, key, value, seed), args.episodes + 1)

    jobs = [(arm, target, seed) for seed in args.seeds for target in args.explore for arm in arms]
    run_all(run, jobs, args.jobs)
    link_experiment(root, family.sources, arms)
    name = f"compliance_{family.task}_explore_learning_curves"
    args.figures.mkdir(parents=True, exist_ok=True)
    figure, *others = plot_learning_curves(discover(root), args.figures / name)
    for other in others:
        other.unlink()
    budget = args.episodes + 1
    results: dict = {}
    lines = [
        f"## Compliance: {family.task}, further targets: PILCO, transfer and the gate",
        "",
        f"{run_header()} Per target and seed, from the "
        f"{family.label(family.source_value)} source of the same seed: "
        + "; ".join(EXPLORE_ARM_HELP[arm].format(approach=args.approach, gate=args.gate) for arm in arms)
        + f". {budget} episodes per run (1 random + {args.episodes} learned), one torch thread each, {args.jobs} in "
        f"parallel. Runs: `{display_path(root)}`. AUC: trapezoid over the {budget} episodes; final: mean of "
        "the last 3.",
        "",
        f"![learning curves, mean ± std over seeds]({figure.relative_to(args.figures.parent)})",
        "",
    ]
    rows = []
    for key, value in args.explore:
        for arm in arms:
            per_seed = []
            for seed in args.seeds:
                curve = Curve.read(run_dir(arm, key, value, seed), budget)
                per_seed.append({"seed": seed, "returns": curve.returns, "compliance": curve.compliance,
                                 "fell_back_after": fell_back_at(run_dir(arm, key, value, seed)), **curve.summary()})
            results.setdefault(f"{key}={value:g}", {})[arm] = per_seed
            rows.append(learning_row(f"{key} = {value:g}", arm, per_seed, gated=arm.startswith("gated")))
    lines += [markdown_table(rows, LEARNING_COLUMNS, LEARNING_ALIGN), "",
              "Returns per episode (target, arm, seed: curve):", ""]
    for target, by_arm in results.items():
        for arm, per_seed in by_arm.items():
            lines += [f"- {target}, {arm}, seed {r['seed']}: " + " ".join(f"{v:.1f}" for v in r["returns"])
                      for r in per_seed]
    return results, "\n".join(lines)


def parse_targets(items: list[str]) -> list[tuple[str, float]]:
    """``KEY=VALUE`` items as (env kwarg, number); ValueError naming the first bad one."""
    targets = []
    for item in items:
        key, _, value = item.partition("=")
        try:
            targets.append((key, float(value)))
        except ValueError:
            raise ValueError(f"--explore takes KEY=VALUE, VALUE a number (e.g. friction=5.0), got {item!r}") from None
        if not key.isidentifier():
            raise ValueError(f"--explore takes KEY=VALUE with KEY an env argument (e.g. friction=5.0), got {item!r}")
    return targets


def measure(family: Family, args: argparse.Namespace) -> dict:
    """The Λ table of ``family`` over ``args.seeds``, written to docs/benchmarks.md; its JSON entry."""
    values = [family.source_value, *family.near, *family.far]
    rows = {v: [initial_compliance(family, v, s, args.overrides) for s in args.seeds] for v in values}
    verdict = compliance_verdict(family, rows)
    section = compliance_section(family, rows, verdict, args.seeds, run_header())
    write_section(f"bench_compliance-{family.task}", section)
    print(section, flush=True)
    return {"date": today(), "commit": commit(), "command": command_line(),
            "machine": machine(), "sources": display_path(family.sources), "verdict": verdict,
            "compliance": {str(v): r for v, r in rows.items()}}

def main() -> None:
    """Λ per family, or the learning runs (``--learn``), or the exploration (``--explore``); JSON and sections."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", nargs="+", choices=list(FAMILIES), default=list(FAMILIES))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--learn", action="store_true", help="also the learning runs: PILCO, transfer, gated")
    parser.add_argument("--gate", type=float, help="transfer.min_compliance of the gated runs (with --learn)")
    parser.add_argument("--arms", nargs="+", choices=ARMS, default=list(ARMS), help="which learning runs")
    parser.add_argument("--gate-on", choices=("all", "far"), default="all",
                        help="gated runs on every target, or on the far ones only (a near target whose Λ at the first "
                             "model is above the gate repeats its ungated run exactly)")
    parser.add_argument("--approach", default="qtl_bayesian", help="the transfer preset, run θ-only")
    parser.add_argument("--episodes", type=int, default=10, help="learned episodes per learning run")
    parser.add_argument("--jobs", type=int, default=2, help="learning runs in parallel (one torch thread each)")
    parser.add_argument("--runs-dir", type=Path, default=ROOT / "runs" / "bench_compliance")
    parser.add_argument("--figures", type=Path, default=ROOT / "docs" / "results",
                        help="where the learning-curve figure goes")
    parser.add_argument("--sources", nargs="*", default=[], metavar="FAMILY=DIR",
                        help="another directory of seed_<k> source runs for a family")
    parser.add_argument("--explore", nargs="+", default=[], metavar="KEY=VALUE",
                        help="other targets of the family, any env argument (e.g. friction=5.0 max_force=5.0): PILCO "
                             "and θ-only transfer on each, for a target where transfer hurts (a table of their own; "
                             "only this: the Λ table and --learn are other calls)")
    parser.add_argument("--explore-arms", nargs="+", choices=EXPLORE_CHOICES,
                        help="the runs per --explore target (default: pilco transfer, and gated with --gate); qtl: "
                             "θ_s and ψ_s, gated_qtl: the same with the gate")
    args, args.overrides = parse_with_overrides(parser)
    try:
        args.explore = parse_targets(args.explore)
    except ValueError as err:
        parser.error(str(err))
    if args.explore and args.learn:
        parser.error("--explore runs on its own: leave out --learn (run it in another call)")
    args.arms = [arm for arm in ARMS if arm in args.arms]
    if args.gate is not None and not 0.0 <= args.gate <= 1.0:
        parser.error(f"--gate must be in [0, 1], got {args.gate}")
    if args.explore_arms and not args.explore:
        parser.error("--explore-arms needs --explore targets")
    if args.explore_arms and any(a.startswith("gated") for a in args.explore_arms) and args.gate is None:
        parser.error("--explore-arms gated and gated_qtl need --gate: the transfer.min_compliance chosen beforehand")
    if args.learn and "gated" in args.arms and (args.gate is None or not 0.0 <= args.gate <= 1.0):
        parser.error("--learn needs --gate in [0, 1]: the transfer.min_compliance chosen from the Λ table")
    families = dict(FAMILIES)
    for item in args.sources:
        name, _, path = item.partition("=")
        if name not in families or not path:
            parser.error(f"--sources takes FAMILY=DIR with FAMILY one of {', '.join(FAMILIES)}, got {item!r}")
        families[name] = dataclasses.replace(families[name], sources=Path(path).resolve())
    for name in args.families:
        missing = [s for s in args.seeds if not (families[name].sources / f"seed_{s}").is_dir()]
        if missing:
            parser.error(f"{name}: no source runs for seeds {missing} in {families[name].sources} "
                         "(make them first, e.g. qtl-train experiment=mountaincar_source)")
    torch.set_num_threads(1)
    register_configs()

    out = ROOT / "docs" / "bench" / "compliance.json"
    stored = json.loads(out.read_text()) if out.exists() else {}
    for name in args.families:
        family = families[name]
        if args.explore:  # only the exploration; the Λ table and the learning runs are left as stored
            entry = stored.get(name, {})
            entry["explore"], table = explore(family, args)
            write_section(f"bench_compliance_explore-{name}", table)
            print(table, flush=True)
        else:
            entry = {**measure(family, args), **{k: v for k, v in stored.get(name, {}).items() if k == "explore"}}
            if args.learn:
                entry["gate"] = args.gate
                entry["learning"], table = learn(family, args)
                write_section(f"bench_compliance_gate-{name}", table)
                print(table, flush=True)
            elif "learning" in stored.get(name, {}):
                entry["gate"], entry["learning"] = stored[name]["gate"], stored[name]["learning"]
        stored[name] = entry
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(stored, indent=2) + "\n")


if __name__ == "__main__":
    main()
