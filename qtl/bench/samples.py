"""Sample transfer (issue 65): PILCO, QTL Bayesian, QTL Bayesian + source samples, samples alone; paired per seed.

The settings, the arms' overrides, one run's figures from its ``metrics.csv`` and ``timings.csv`` rows, the paired
comparisons and the issue's two goals, and the Markdown section of a setting (``scripts/bench_samples.py`` runs it).

Goal (a), at cart-pole 1.0 kg: ``qtl_bayesian_samples`` succeeds first at an earlier episode than ``qtl_bayesian`` in
at least 4 of 5 paired seeds (a run that never succeeds counts as the budget). Goal (b), at mountain car 3.0 power,
"the sample arms never learn worse than PILCO", operationalised per seed: in every paired seed, each sample arm's AUC
is at least PILCO's minus 5 % of |PILCO's AUC|. A goal is judged only when all 5 seeds of the arms it reads finished.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass
from typing import Any

from qtl.bench.cells import markdown_table, mean_std
from qtl.bench.runs import curve_figures

ARMS = ("pilco", "qtl_bayesian", "qtl_bayesian_samples", "samples")
SAMPLE_ARMS = ("qtl_bayesian_samples", "samples")
ARM_OVERRIDES: dict[str, tuple[str, ...]] = {
    "pilco": (),
    "qtl_bayesian": ("approach=qtl_bayesian",),
    "qtl_bayesian_samples": ("approach=qtl_bayesian", "transfer.samples=relevance"),
    "samples": ("rule=none", "transfer.hyperparameters=false", "transfer.samples=relevance"),
}
ARM_LABELS = {
    "pilco": "PILCO (no transfer)",
    "qtl_bayesian": "QTL Bayesian (θ_s, ψ_s)",
    "qtl_bayesian_samples": "QTL Bayesian + samples",
    "samples": "samples alone (no θ_s, no ψ_s)",
}
JUDGED_SEEDS = 5  # a goal is judged on this many paired seeds ...
REQUIRED_EARLIER = 4  # ... goal (a): samples earlier than QTL Bayesian in at least this many of them
AUC_TOLERANCE = 0.05  # goal (b): a sample arm's AUC ≥ PILCO's − this fraction of |PILCO's AUC|, every seed
TOLERANCE_TEXT = f"{AUC_TOLERANCE * 100:g} %"
GOAL_A_SETTING = "cartpole-1.0"
GOAL_B_SETTING = "mountaincar-3.0"


@dataclass(frozen=True)
class Setting:
    """A source → target pair of one task family along ``task.env.<axis>``, with the family's transfer budget."""

    name: str
    task: str
    axis: str
    unit: str
    source_value: float
    target_value: float
    episodes: int  # learned episodes per target run (after the initial one)
    overrides: tuple[str, ...] = ()  # the family's transfer benchmark's target overrides

    def label(self, value: float) -> str:
        """A value of the axis as the tables write it: '150 %' or '2.0 kg'."""
        return f"{value * 100:g} %" if self.unit == "%" else f"{value:.1f} {self.unit}"

    def title(self) -> str:
        """The setting in words: 'mountaincar 100 % → 300 %'."""
        return f"{self.task} {self.label(self.source_value)} → {self.label(self.target_value)}"

    def target_overrides(self, arm: str, seed: int, source: str | None, extra: list[str]) -> list[str]:
        """The overrides of the target run of ``arm`` and ``seed`` (``source``: the source run, QTL arms only)."""
        transfer = [f"transfer.source={source}"] if arm != "pilco" else []
        return [f"task={self.task}", f"task.env.{self.axis}={self.target_value:g}", f"seed={seed}",
                f"episodes={self.episodes}", *self.overrides, *ARM_OVERRIDES[arm], *transfer, *extra]


# Budgets: mountain car as bench_compliance.py --learn's recorded table (--episodes 6, defaults otherwise); cart-pole
# as bench_transfer.py's recorded tables (--episodes 7, optimizer.restarts=1).
SETTINGS = {
    "mountaincar-1.5": Setting("mountaincar-1.5", "mountaincar", "power", "%", 1.0, 1.5, 6),
    "mountaincar-3.0": Setting("mountaincar-3.0", "mountaincar", "power", "%", 1.0, 3.0, 6),
    "cartpole-1.0": Setting("cartpole-1.0", "cartpole", "pole_mass", "kg", 0.5, 1.0, 7, ("optimizer.restarts=1",)),
    "cartpole-2.0": Setting("cartpole-2.0", "cartpole", "pole_mass", "kg", 0.5, 2.0, 7, ("optimizer.restarts=1",)),
}


def _number(text: str | None) -> float | None:
    """A CSV cell as a number; None for an empty cell or NaN."""
    if text is None or text == "":
        return None
    value = float(text)
    return None if math.isnan(value) else value


def run_result(seed: int, metrics: list[dict[str, str]], timings: list[dict[str, str]], budget: int) -> dict[str, Any]:
    """One finished run's figures: curve, first success, AUC, fit and search time per learned episode, samples."""
    if len(metrics) < budget or len(timings) < budget:
        raise ValueError(f"{min(len(metrics), len(timings))} episodes, {budget} needed")
    rows, learned = metrics[:budget], timings[1:budget]  # the model is fitted before each learned episode
    last = rows[-1]
    return {
        "seed": seed,
        **curve_figures(rows),
        "model_fit_s_per_episode": statistics.mean(float(t["model_fit_s"]) for t in learned),
        "policy_search_s_per_episode": statistics.mean(float(t["policy_search_s"]) for t in learned),
        "source_samples": [_number(r.get("source_samples")) for r in rows],
        "relevance": [_number(r.get("relevance")) for r in rows],
        "effective_samples": [_number(r.get("effective_samples")) for r in rows],
        "last_source_samples": _number(last.get("source_samples")),
        "last_relevance": _number(last.get("relevance")),
        "last_effective_samples": _number(last.get("effective_samples")),
    }


def to_success(result: dict[str, Any], budget: int) -> int:
    """A run's first success, the budget for a run that never succeeds."""
    return budget if result["first_success"] is None else result["first_success"]


def paired(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """The finished runs of two arms that share a seed, in seed order."""
    by_seed = {r["seed"]: r for r in b}
    return [(r, by_seed[r["seed"]]) for r in sorted(a, key=lambda r: r["seed"]) if r["seed"] in by_seed]


def first_success_pairs(arm: list[dict[str, Any]], baseline: list[dict[str, Any]], budget: int) -> dict[str, Any]:
    """Per paired seed, ``arm``'s first success against ``baseline``'s: earlier, same or later; and the counts."""
    per_seed = []
    for r, b in paired(arm, baseline):
        mine, theirs = to_success(r, budget), to_success(b, budget)
        verdict = "earlier" if mine < theirs else "same" if mine == theirs else "later"
        per_seed.append({"seed": r["seed"], "arm": mine, "baseline": theirs, "verdict": verdict})
    counts = {v: sum(p["verdict"] == v for p in per_seed) for v in ("earlier", "same", "later")}
    return {"per_seed": per_seed, **counts, "paired": len(per_seed)}


def auc_pairs(arm: list[dict[str, Any]], baseline: list[dict[str, Any]]) -> dict[str, Any]:
    """Per paired seed, ``arm``'s AUC minus ``baseline``'s, and whether it is within the goal's tolerance."""
    per_seed = [{"seed": r["seed"], "difference": r["auc"] - b["auc"],
                 "not_worse": r["auc"] >= b["auc"] - AUC_TOLERANCE * abs(b["auc"])} for r, b in paired(arm, baseline)]
    differences = [p["difference"] for p in per_seed]
    return {"per_seed": per_seed, "paired": len(per_seed),
            "mean_difference": statistics.mean(differences) if differences else None,
            "not_worse": sum(p["not_worse"] for p in per_seed)}


def goal_a(arms: dict[str, list[dict[str, Any]]], budget: int) -> dict[str, Any]:
    """Goal (a): QTL Bayesian + samples succeeds earlier than QTL Bayesian in ≥ 4 of 5 paired seeds."""
    pairs = first_success_pairs(arms.get("qtl_bayesian_samples", []), arms.get("qtl_bayesian", []), budget)
    judged = pairs["paired"] >= JUDGED_SEEDS
    return {"goal": f"QTL Bayesian + samples succeeds earlier than QTL Bayesian in ≥ {REQUIRED_EARLIER} of "
                    f"{JUDGED_SEEDS} paired seeds", "earlier": pairs["earlier"], "paired": pairs["paired"],
            "passed": pairs["earlier"] >= REQUIRED_EARLIER if judged else None}


def goal_b(arms: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    """Goal (b): in every paired seed, each sample arm's AUC ≥ PILCO's − 5 % of |PILCO's AUC|."""
    pairs = {arm: auc_pairs(arms.get(arm, []), arms.get("pilco", [])) for arm in SAMPLE_ARMS}
    judged = all(p["paired"] >= JUDGED_SEEDS for p in pairs.values())
    return {"goal": f"every sample arm's AUC ≥ PILCO's − {TOLERANCE_TEXT} of |PILCO's AUC| in every paired seed",
            "not_worse": {arm: p["not_worse"] for arm, p in pairs.items()},
            "paired": {arm: p["paired"] for arm, p in pairs.items()},
            "passed": all(p["not_worse"] == p["paired"] for p in pairs.values()) if judged else None}


def status(passed: bool | None) -> str:
    """A goal's verdict in words."""
    return {True: "met", False: "NOT met", None: "not judged: a partial run"}[passed]


def _mean(values: list[float | None], digits: int) -> str:
    """Mean ± std of the values present ('—' for none)."""
    return mean_std([v for v in values if v is not None], digits)


def comparisons(arms: dict[str, list[dict[str, Any]]], budget: int) -> dict[str, Any]:
    """The paired comparisons of a setting: samples against QTL Bayesian (first success), sample arms against PILCO."""
    return {"first_success_qtl_bayesian_samples_vs_qtl_bayesian":
            first_success_pairs(arms.get("qtl_bayesian_samples", []), arms.get("qtl_bayesian", []), budget),
            **{f"auc_{arm}_vs_pilco": auc_pairs(arms.get(arm, []), arms.get("pilco", [])) for arm in SAMPLE_ARMS}}


def section(setting: Setting, info: dict[str, Any]) -> list[str]:
    """The Markdown section of one setting: how it ran, the goal, the arms' table, the paired comparisons."""
    m, budget, arms, seeds = info["machine"], info["episodes_per_run"], info["arms"], info["seeds"]
    goal = info.get("goal")
    lines = [
        f"## Sample transfer: {setting.title()}",
        "",
        f"`{info['command']}` at commit {info['commit']} — {info['date']}, {m['cpu']} ({m['cores']} cores), "
        f"{info['jobs']} run(s) in parallel with {info['threads']} torch thread(s) each, torch {m['torch']}. "
        f"{budget} episodes per target run (1 initial + {budget - 1} learned); target overrides: "
        f"`{' '.join(setting.overrides) or 'none'}`. Sources per seed k: `{info['sources']}`. Arms: PILCO; QTL "
        "Bayesian (`approach=qtl_bayesian`: θ_s, ψ_s, the Bayesian rule); the same + `transfer.samples=relevance`; "
        "samples alone (`rule=none transfer.hyperparameters=false transfer.samples=relevance`, random initial "
        f"episode). Up to `transfer.max_source_samples` = 200 source tuples. First success: the task's own test, "
        f"episode 0 the initial one, a run that never succeeds counted as {budget} (the budget) in the mean. AUC: "
        f"trapezoid over the {budget} episodes. Relevance, effective samples: the last episode's model. Results: "
        f"`{info['output']}`.",
        "",
    ]
    if goal is not None:
        lines += [f"**Goal: {goal['goal']} — {status(goal['passed'])}.**", ""]
    rows = []
    for arm in ARMS:
        done = arms.get(arm, [])
        missing = [s for s in seeds if s not in {r["seed"] for r in done}]
        per_seed = " ".join("not run" if s in missing else
                            next("—" if r["first_success"] is None else str(r["first_success"])
                                 for r in done if r["seed"] == s) for s in seeds)
        sample = arm in SAMPLE_ARMS
        rows.append([ARM_LABELS[arm], per_seed,
                     _mean([to_success(r, budget) for r in done], 1),
                     f"{sum(r['first_success'] is not None for r in done)}/{len(done)}"
                     + (f" ({len(missing)} not run)" if missing else ""),
                     _mean([r["auc"] for r in done], 1), _mean([r["final_performance"] for r in done], 1),
                     _mean([r["last_relevance"] for r in done], 3) if sample else "",
                     _mean([r["last_effective_samples"] for r in done], 1) if sample else "",
                     _mean([r["model_fit_s_per_episode"] for r in done], 2),
                     _mean([r["policy_search_s_per_episode"] for r in done], 1)])
    lines.append(markdown_table(rows, ["arm", "first success per seed", "first success (mean)", "solved", "AUC",
                                       "final", "relevance (last)", "effective samples (last)",
                                       "model fit (s/episode)", "policy search (s/episode)"], "llrrrrrrrr"))
    comp = info["comparisons"]
    fs = comp["first_success_qtl_bayesian_samples_vs_qtl_bayesian"]
    lines += ["", "Paired per seed (seed: first success of QTL Bayesian + samples vs QTL Bayesian): "
              + (", ".join(f"{p['seed']}: {p['arm']} vs {p['baseline']} ({p['verdict']})" for p in fs["per_seed"])
                 or "no paired seed") + f" — earlier in {fs['earlier']}, same in {fs['same']}, later in "
              f"{fs['later']} of {fs['paired']}."]
    for arm in SAMPLE_ARMS:
        auc = comp[f"auc_{arm}_vs_pilco"]
        mean = "—" if auc["mean_difference"] is None else f"{auc['mean_difference']:+.1f}"
        lines += ["", f"AUC of {ARM_LABELS[arm]} minus PILCO's per seed: "
                  + (", ".join(f"{p['seed']}: {p['difference']:+.1f}" for p in auc["per_seed"]) or "no paired seed")
                  + f" (mean {mean}; within {TOLERANCE_TEXT} of PILCO's |AUC| or above in {auc['not_worse']} of "
                  f"{auc['paired']})."]
    lines += ["", "Returns per episode (arm, seed: curve; relevance per episode for the sample arms):", ""]
    for arm in ARMS:
        for r in arms.get(arm, []):
            extra = ("; relevance " + " ".join("—" if w is None else f"{w:.2f}" for w in r["relevance"])
                     if arm in SAMPLE_ARMS else "")
            lines.append(f"- {arm}, seed {r['seed']}: " + " ".join(f"{v:.1f}" for v in r["returns"]) + extra)
    return lines
