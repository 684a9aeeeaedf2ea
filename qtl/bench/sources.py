"""Source choice (issue 65): a library of sources along one physical parameter, one target, and who chooses what.

A family is a task, its transfer axis (``task.env.<axis>``), a library of source values and a target value. The
source nearest the target is the one nearest in **log distance** |log(v / target)|, i.e. by ratio, not by |Δ|:
the cart-pole's pole masses 1.0 kg and 3.0 kg are equally far from 2.0 kg by |Δ| (1.0 kg each, a tie), but
3.0 / 2.0 = 1.5 against 2.0 / 1.0 = 2.0 makes 3.0 kg the nearer (the dynamics scale with the mass ratio). For the
mountain car's 150 % target, 100 % (ratio 1.5) is nearer than 300 % (ratio 2.0), and |Δ| agrees.

The arms of a target seed (``ARMS``): ``transfer.select=compliance`` over the whole library, ``select=mixture``, each
source alone, and PILCO; the transfer arms run the ``qtl_bayesian`` preset (θ_s and ψ_s). This module holds the
benchmark's pure logic: the families, each arm's overrides, a run's figures from its ``metrics.csv`` rows, the
verdicts and the Markdown section; ``scripts/bench_sources.py`` makes the runs.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from qtl.bench.cells import markdown_table, mean_std
from qtl.bench.runs import curve_figures

APPROACH = "qtl_bayesian"  # the transfer arms' preset, as bench_transfer's qtl_bayesian: θ_s and ψ_s transferred
SELECTS = ("compliance", "mixture")  # the arms over the whole library, by their transfer.select
PILCO = "pilco"
REQUIRED_SEEDS = 4  # select=compliance picks the nearest source in at least this many of ...
JUDGED_SEEDS = 5  # ... this many seeds; fewer finished seeds are not judged
SOURCE_SEED = 0  # the library: one source run per value, this seed


@dataclass(frozen=True)
class Family:
    """A task, its transfer axis, the library's values, the target value and the runs' budgets (learned episodes).

    ``reuse``: a value whose source is another benchmark's run (its directory relative to the repository, and the
    overrides that made it), used when those overrides compose the same config as this benchmark's own.
    """

    task: str
    axis: str
    unit: str
    sources: tuple[float, ...]
    target: float
    source_episodes: int
    episodes: int
    reuse: tuple[tuple[float, str, tuple[str, ...]], ...] = ()

    def label(self, value: float) -> str:
        """A value as the tables write it: '150 %' or '2.0 kg'."""
        return f"{value * 100:g} %" if self.unit == "%" else f"{value:.1f} {self.unit}"

    def value_override(self, value: float) -> str:
        """``task.env.<axis>=<value>``."""
        return f"task.env.{self.axis}={value:g}"

    def source_overrides(self, value: float) -> list[str]:
        """The overrides of the library's run at ``value``: the source seed, its budget, the task and the value."""
        return [f"seed={SOURCE_SEED}", f"episodes={self.source_episodes}", f"task={self.task}",
                self.value_override(value)]

    def source_dir(self, runs_dir: Path, value: float) -> Path:
        """Where this benchmark makes the library's run at ``value``."""
        return runs_dir / self.task / "source" / f"{self.axis}{value:g}" / f"seed_{SOURCE_SEED}"

    def reused(self, value: float) -> tuple[str, list[str]] | None:
        """Another benchmark's run that may serve as the source at ``value``: (directory, its overrides)."""
        return next(((path, list(made_by)) for v, path, made_by in self.reuse if v == value), None)


FAMILIES = {
    # Budgets: the mountain car's learning runs (bench_kinematic: within 8, i.e. 7 learned) for the sources, its
    # transfer runs (bench_compliance --learn --episodes 6, the recorded table) for the targets.
    "mountaincar": Family("mountaincar", "power", "%", (0.5, 1.0, 3.0), 1.5, source_episodes=7, episodes=6),
    # bench_cartpole (within 8: 7 learned) for the sources, its 0.5 kg run of seed 0 reused; bench_transfer's
    # recorded table (--episodes 7) for the targets.
    "cartpole": Family("cartpole", "pole_mass", "kg", (0.5, 1.0, 3.0), 2.0, source_episodes=7, episodes=7,
                       reuse=((0.5, "runs/bench_cartpole/cartpole/seed_0", ("seed=0", "episodes=7")),)),
}


def log_distance(value: float, target: float) -> float:
    """|log(value / target)|: how far apart two values of a physical parameter are, by their ratio."""
    return abs(math.log(value / target))


def nearest(values: tuple[float, ...] | list[float], target: float) -> float:
    """The value nearest ``target`` in log distance; ValueError on a tie (no nearest source to require)."""
    ranked = sorted(values, key=lambda v: log_distance(v, target))
    if len(ranked) > 1 and math.isclose(log_distance(ranked[0], target), log_distance(ranked[1], target)):
        raise ValueError(f"{ranked[0]:g} and {ranked[1]:g} are equally near {target:g}")
    return ranked[0]


def single_arm(family: Family, value: float) -> str:
    """The slug of the arm that transfers from the source at ``value`` alone."""
    return f"single_{family.axis}{value:g}"


def arms(family: Family) -> list[str]:
    """The arms of a target seed, in the table's order: the selects, each source alone, PILCO."""
    return [*SELECTS, *(single_arm(family, v) for v in family.sources), PILCO]


def arm_label(family: Family, arm: str) -> str:
    """How the table names an arm."""
    if arm in SELECTS:
        return f"select={arm} (all {len(family.sources)} sources)"
    if arm == PILCO:
        return "PILCO (no transfer)"
    value = next(v for v in family.sources if single_arm(family, v) == arm)
    return f"{family.label(value)} alone"


def arm_overrides(family: Family, arm: str, seed: int, episodes: int, sources: list[str],
                  extra: list[str]) -> list[str]:
    """The overrides of a target run: the target, seed and budget, then the arm's transfer, then ``extra``.

    ``sources``: the library's run directories in the order of ``family.sources`` (k of ``compliance/<k>``).
    """
    common = [f"task={family.task}", family.value_override(family.target), f"seed={seed}", f"episodes={episodes}"]
    if arm in SELECTS:
        transfer = [f"approach={APPROACH}", f"transfer.source=[{','.join(sources)}]", f"transfer.select={arm}"]
    elif arm == PILCO:
        transfer = []
    else:
        index = arms(family).index(arm) - len(SELECTS)
        transfer = [f"approach={APPROACH}", f"transfer.source={sources[index]}"]
    return [*common, *transfer, *extra]


def _number(text: str | None) -> float | None:
    """A CSV cell as a number; None for an empty cell or NaN."""
    if text is None or text == "":
        return None
    value = float(text)
    return None if math.isnan(value) else value


def seed_result(seed: int, rows: list[dict[str, str]], budget: int, values: tuple[float, ...]) -> dict[str, Any]:
    """One target run's figures from its ``metrics.csv`` rows (the first ``budget``): curve, AUC, choice, Λ_k.

    ``values``: the library's values in the order of ``transfer.source``, so that ``selected_source`` k reads as
    ``values[k]``. A run of one source or none has no choice (None) and no per-source Λ.
    """
    if len(rows) < budget:
        raise ValueError(f"{len(rows)} episodes, {budget} needed")
    rows = rows[:budget]
    chosen = [int(k) for k in (_number(r.get("selected_source")) for r in rows) if k is not None]
    by_source = [[_number(r.get(f"compliance/{k}")) for k in range(len(values))] for r in rows]
    first_model = next((i for i, lam in enumerate(by_source) if any(x is not None for x in lam)), None)
    return {
        "seed": seed,
        **curve_figures(rows),
        "selected_source": chosen[-1] if chosen else None,
        "selected_value": values[chosen[-1]] if chosen else None,
        "selection_constant": len(set(chosen)) <= 1,
        "compliance_first_model": None if first_model is None else by_source[first_model],
        "compliance_last": by_source[-1] if first_model is not None else None,
    }


def selection_verdict(family: Family, per_seed: list[dict[str, Any]], seeds: list[int]) -> dict[str, Any]:
    """Required: select=compliance picks the nearest source (log distance) in ≥ 4 of 5 seeds.

    ``per_seed``: the compliance arm's finished seeds; ``seeds``: every seed asked for. Judged with at least 5 seeds
    asked for, all finished (``passed`` None otherwise).
    """
    near = nearest(family.sources, family.target)
    hits = [r["seed"] for r in per_seed if r["selected_value"] == near]
    judged = len(seeds) >= JUDGED_SEEDS and len(per_seed) == len(seeds)
    return {"nearest": near, "picked_nearest": len(hits), "finished": len(per_seed), "seeds": len(seeds),
            "seeds_picking_nearest": hits, "passed": len(hits) >= REQUIRED_SEEDS if judged else None}


def goal_verdict(family: Family, results: dict[str, list[dict[str, Any]]], seeds: list[int]) -> dict[str, Any]:
    """Goal: the compliance arm's mean AUC at least the mean of the single-source arms' mean AUCs.

    Judged only when every one of these arms finished every seed (``passed`` None otherwise).
    """
    singles = [single_arm(family, v) for v in family.sources]
    means = {arm: statistics.mean(r["auc"] for r in results[arm]) if results.get(arm) else None
             for arm in ["compliance", *singles]}
    complete = all(len(results.get(arm, [])) == len(seeds) for arm in means)
    single_means = [means[a] for a in singles if means[a] is not None]
    single_mean = statistics.mean(single_means) if single_means else None
    passed = means["compliance"] >= single_mean if complete and single_mean is not None else None
    return {"compliance_mean_auc": means["compliance"], "single_source_mean_auc": single_mean, "passed": passed}


def resume_command(command: str) -> str:
    """``command`` as it completes every run: without ``--no-run``, nor ``--arms`` and the arms after it."""
    kept, skipping = [], False
    for token in command.split():
        if token in ("--no-run", "--arms"):
            skipping = token == "--arms"
            continue
        if skipping and not token.startswith("-") and "=" not in token:
            continue
        skipping = False
        kept.append(token)
    return " ".join(kept)


def _status(passed: bool | None) -> str:
    return {True: "met", False: "NOT met", None: "not judged: a partial run"}[passed]


def _cell(value: float | None, digits: int = 2) -> str:
    return "—" if value is None else f"{value:.{digits}f}"


def _reuse_note(family: Family, info: dict[str, Any]) -> str:
    """What the section says of library runs reused from another benchmark, and of their torch threads."""
    notes = []
    for value in family.sources:
        key = f"{value:g}"
        if info.get("source_reused", {}).get(key):
            threads = info.get("source_threads", {}).get(key)
            notes.append(f"the {family.label(value)} source is another benchmark's run, reused: made by "
                         f"`{' '.join(info['source_overrides'][key])}`, which composes the same config"
                         + (f", with {threads} torch threads" if threads is not None else ""))
    return "; " + "; ".join(notes) if notes else ""


def section(family: Family, info: dict[str, Any]) -> list[str]:
    """The Markdown section of one family: settings, both verdicts, the choice per seed and the arms' figures."""
    m, results, seeds = info["machine"], info["results"], info["seeds"]
    select, goal = info["selection"], info["goal"]
    budget = info["episodes_per_run"]
    library = ", ".join(family.label(v) for v in family.sources)
    distances = ", ".join(f"{family.label(v)}: {log_distance(v, family.target):.3f}" for v in family.sources)
    lines = [
        f"## Source choice: {family.task}, library {library} → {family.label(family.target)}",
        "",
        f"`{info['command']}` at commit {info['commit']} — {info['date']}, {m['cpu']} ({m['cores']} cores), "
        f"{info['jobs']} run(s) in parallel with {info['threads']} torch thread(s) each, torch {m['torch']}. "
        f"Library: one source run per value, seed {SOURCE_SEED}, learned from scratch "
        f"({info.get('source_episodes_per_run', family.source_episodes + 1)} episodes: "
        f"{', '.join(info['sources'].values())}){_reuse_note(family, info)}. Per target seed, {budget} episodes per "
        "run (1 initial + "
        f"{budget - 1} learned): `transfer.select=compliance` and `select=mixture` over the library (k of "
        f"`compliance/<k>` in the order {library}; initial episode random, ψ_s of the chosen source before the first "
        f"search), each source alone (initial episode by its ψ_s), all `approach={APPROACH}` (θ_s and ψ_s), and "
        f"PILCO. Target overrides: `{' '.join(info['overrides']) or 'none'}`. First success: the task's own test "
        f"(episode 0 is the initial one); AUC: trapezoid over the {budget} episodes, mean ± std over seeds. Results: "
        f"`{info['output']}`.",
        "",
        f"Nearest source: by log distance |log(v / {family.target:g})| ({distances}), i.e. by ratio"
        + (", not by |Δ|, under which 1.0 kg and 3.0 kg tie at 1.0 kg from 2.0 kg" if family.axis == "pole_mass"
           else "; |Δ| agrees") + f": **{family.label(select['nearest'])}**.",
        "",
        f"**Required: select=compliance picks the nearest source in at least {REQUIRED_SEEDS} of {JUDGED_SEEDS} "
        "seeds — "
        f"{_status(select['passed'])} ({select['picked_nearest']} of {select['finished']} finished seeds, "
        f"{select['seeds']} asked for).**",
        "",
        "**Goal: select=compliance's mean AUC at least the mean of the single-source arms' — "
        f"{_status(goal['passed'])} "
        f"({_cell(goal['compliance_mean_auc'], 1)} vs {_cell(goal['single_source_mean_auc'], 1)}).**",
        "",
        "The AUC counts the initial episode: random in the arms over the library (no source is preferred before the "
        "first model), run by ψ_s in each single-source arm.",
        "",
    ]
    by_seed = {arm: {r["seed"]: r for r in results.get(arm, [])} for arm in SELECTS}
    rows = []
    for seed in seeds:
        comp, mix = by_seed["compliance"].get(seed), by_seed["mixture"].get(seed)
        lam = comp["compliance_first_model"] if comp and comp["compliance_first_model"] else [None] * len(
            family.sources)
        rows.append([seed, *(_cell(x) for x in lam),
                     "not run" if comp is None else family.label(comp["selected_value"]),
                     "—" if comp is None else ("yes" if comp["selected_value"] == select["nearest"] else "no"),
                     "not run" if mix is None else family.label(mix["selected_value"])])
    lines += [markdown_table(rows, ["seed", *(f"Λ_{k} ({family.label(v)}), first model"
                                              for k, v in enumerate(family.sources)),
                                    "select=compliance chose", "nearest?", "select=mixture: ψ_s from"],
                             "r" + "r" * len(family.sources) + "lll"), ""]
    rows = []
    for arm in arms(family):
        done = results.get(arm, [])
        missing = [s for s in seeds if s not in {r["seed"] for r in done}]
        rows.append([arm_label(family, arm),
                     " ".join("not run" if s in missing else
                              next("—" if r["first_success"] is None else str(r["first_success"])
                                   for r in done if r["seed"] == s) for s in seeds),
                     f"{sum(r['first_success'] is not None for r in done)}/{len(done)}",
                     mean_std([r["auc"] for r in done]), mean_std([r["final_performance"] for r in done]),
                     f"{len(done)}/{len(seeds)}" + (f" (not run: {' '.join(map(str, missing))})" if missing else "")])
    lines.append(markdown_table(rows, ["arm", "first success per seed", "solved", "AUC", "final performance",
                                       "seeds finished"], "llrrrl"))
    lines += ["", "Returns per episode (arm, seed: curve):", ""]
    for arm in arms(family):
        lines += [f"- {arm_label(family, arm)}, seed {r['seed']}: " + " ".join(f"{v:.1f}" for v in r["returns"])
                  for r in results.get(arm, [])]
    if info.get("error"):
        lines += ["", "Some runs failed: their errors are in the JSON (`error`)."]
    if info.get("unfinished"):
        lines += ["", f"Not run yet ({len(info['unfinished'])} runs): resume with `{info['resume']}`."]
    return lines
