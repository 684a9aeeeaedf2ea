"""TensorBoard dashboards of a run: its HParams session (choices and outcomes), custom scalar layouts, text.

A sweep directory opened in TensorBoard then compares its runs in the HParams table: each run
writes, once (not again on resume), the HParams experiment and session-start summaries of its
choices (:func:`run_hparams`), and after every episode its outcome metrics (:func:`outcomes`) as
``outcome/...`` scalars at that episode's step; the HParams plugin reads each metric's value at the
last step, so a finished (or resumed and finished) run shows its final outcomes.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from typing import Any

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from tensorboard.plugins.hparams import summary_v2 as hp
from torch.utils.tensorboard import SummaryWriter

from qtl.metrics import CONVERGED_FRACTION, FINAL_EPISODES, area_under_curve, final_performance, first_success
from qtl.models import GPHyperparameters
from qtl.recorder import THETA_P_PREFIX, THETA_PREFIX
from qtl.task import Task
from qtl.transfer.plan import SOURCE_COMPLIANCE_PREFIX, TransferPlan

OUTCOME_PREFIX = "outcome"
ENV_PREFIX = "env"  # hyper-parameter names of the target's env kwargs: env/pole_mass, ...
# The outcome metrics of the HParams table: tag -> (display name, description).
OUTCOMES: dict[str, tuple[str, str]] = {
    f"{OUTCOME_PREFIX}/final_performance": (
        "final performance", f"mean total reward of the last {FINAL_EPISODES} episodes (Table 1)"),
    f"{OUTCOME_PREFIX}/auc": (
        "AUC", "area under the learning curve: trapezoidal rule over all episodes, unit spacing (Table 2)"),
    f"{OUTCOME_PREFIX}/first_success": (
        "first success", "episode (0 = the first initial episode) of the first success; NaN: none yet"),
    f"{OUTCOME_PREFIX}/time_to_convergence": (
        "time to 95 %", f"first episode whose total reward reaches {CONVERGED_FRACTION:.0%} of the final "
        "performance (Table 3); NaN: none"),
    f"{OUTCOME_PREFIX}/last_compliance": (
        "last compliance", "task compliance Λ (Eq. 14) of the last episode that computed it; NaN: none"),
    f"{OUTCOME_PREFIX}/wall_time_s": (
        "wall time (s)", "sum of the episodes' wall times (rollouts, model fits, policy searches), resumes included"),
}
CONFIG_TAG = "run/config"
PLAN_TAG = "run/transfer_plan"
RETURNS_CATEGORY = "returns"
RETURN_CHART = "real vs predicted return"
RETURN_TAGS = ("eval/return", "policy/predicted_return")
DEFAULT_APPROACH = "pilco"  # qtl.report.approaches.DEFAULT_APPROACH (not imported: it loads pandas)
CUSTOM_APPROACH = "custom"  # transfer keys set by hand, not by an approach preset
# Rules whose θ_i is θ_p_i, Eq. 7 with γ = 0 (DESIGN.md: "PILCO (γ = 0)"); the Bayesian rule has no γ (NaN,
# which the HParams table leaves blank).
RULES_WITH_ZERO_GAMMA = ("none", "free")
THETA_CATEGORY = "θ_i vs θ_p_i: {output}"
TRANSFER_CATEGORY = "transfer"
COMPLIANCE_CHART = "task compliance Λ_k per source"


def outcomes(rows: Sequence[Mapping[str, Any]], timings: Sequence[Mapping[str, Any]] = ()) -> dict[str, float]:
    """The outcome metrics of :data:`OUTCOMES` from a run's episode rows and timings (as recorded or read back).

    The summaries are :mod:`qtl.metrics`'s, those of ``qtl-report``'s tables, over every episode
    of the run (the initial ones included); an undefined one is NaN.
    """
    returns = [float(r["return"]) for r in rows]
    first = first_success([bool(int(float(r["success"]))) for r in rows])
    compliance = [c for c in (_number(r.get("compliance")) for r in rows) if not math.isnan(c)]
    wall = [_number(t.get("episode_s")) for t in timings]
    values = {
        "final_performance": final_performance(returns),
        "auc": area_under_curve(returns),
        "first_success": math.nan if first is None else float(first),
        "time_to_convergence": _time_to_convergence(returns),
        "last_compliance": compliance[-1] if compliance else math.nan,
        "wall_time_s": math.fsum(w for w in wall if not math.isnan(w)),
    }
    return {f"{OUTCOME_PREFIX}/{name}": float(value) for name, value in values.items()}


def _time_to_convergence(returns: Sequence[float]) -> float:
    """:func:`qtl.metrics.time_to_convergence`, NaN where no episode reaches it (a negative final performance)."""
    target = CONVERGED_FRACTION * final_performance(returns)
    return float(next((i for i, r in enumerate(returns) if r >= target), math.nan))


def _number(value: Any) -> float:
    """A metrics cell as a float: NaN where empty or missing."""
    return math.nan if value is None or value == "" else float(value)


def approach_of(has_source: bool, rule: str) -> str:
    """The run's ``approach=`` preset as Hydra chose it; without one, PILCO when nothing is transferred, else custom."""
    choice = HydraConfig.get().runtime.choices.get("approach") if HydraConfig.initialized() else None
    if choice is not None:
        return str(choice)
    return DEFAULT_APPROACH if not has_source and rule == "none" else CUSTOM_APPROACH


def run_hparams(cfg: Mapping[str, Any], approach: str, rule: str, gamma: float | None) -> dict[str, Any]:
    """The run's choices as HParams values: the same names for every run of a task, so a sweep's table lines up.

    ``task``, ``env/<kwarg>`` (the task's env kwargs, the transfer target), ``approach`` (the
    ``configs/approach`` preset), ``source`` (the source run directory; "" for none), ``theta_s`` and
    ``psi_s`` (what is transferred), ``rule`` and ``gamma`` (the forgetting factor; None: NaN, for a rule
    without one), ``propagation`` (the propagator class in snake case) and ``seed``.
    """
    transfer = cfg.get("transfer") or {}
    source = transfer.get("source")
    values: dict[str, Any] = {"task": str(cfg["task"]["name"])}
    for key, value in cfg["task"]["env"].items():
        if key != "id":
            values[f"{ENV_PREFIX}/{key}"] = value if isinstance(value, bool | int | float | str) else str(value)
    target = str(cfg["propagation"].get("_target_", "")).rpartition(".")[2]
    values.update(
        approach=approach,
        source="" if source is None else str(source),
        theta_s=bool(source is not None and transfer.get("hyperparameters", True) and rule != "none"),
        psi_s=bool(source is not None and transfer.get("policy", False)),
        rule=rule,
        gamma=math.nan if gamma is None else float(gamma),
        propagation=re.sub(r"(?<!^)(?=[A-Z])", "_", target).lower(),
        seed=int(cfg["seed"]),
    )
    return values


def write_session(writer: SummaryWriter, hparams: Mapping[str, Any]) -> None:
    """The HParams experiment (these names, the :data:`OUTCOMES` metrics) and session start into ``writer``'s run."""
    metrics = [hp.Metric(tag, display_name=name, description=text) for tag, (name, text) in OUTCOMES.items()]
    file_writer = writer.file_writer  # this run's own events file (add_hparams would open another run)
    file_writer.add_summary(hp.hparams_config_pb([hp.HParam(name) for name in hparams], metrics), 0)
    file_writer.add_summary(hp.hparams_pb(dict(hparams)), 0)


def write_outcomes(writer: SummaryWriter, values: Mapping[str, float], step: int) -> None:
    """The outcome metrics as scalars at ``step`` (NaN included: the value at the last step is the run's)."""
    for tag, value in values.items():
        writer.add_scalar(tag, value, step)
    writer.flush()


def scalar_layout(num_outputs: int, input_dim: int,
                  outputs: Sequence[int] | None = None) -> dict[str, dict[str, list[Any]]]:
    """Custom scalar charts: real vs predicted return; per output dimension, θ_i and θ_p_i of each hyper-parameter.

    ``outputs``: the state dimension each output models (default 0..E−1), which names its charts.
    """
    layout: dict[str, dict[str, list[Any]]] = {
        RETURNS_CATEGORY: {RETURN_CHART: ["Multiline", [f"^{re.escape(t)}$" for t in RETURN_TAGS]]}}
    for j in range(num_outputs) if outputs is None else outputs:
        prefix = f"out{j}/"
        charts = {}
        for key in GPHyperparameters.keys(num_outputs, input_dim, outputs):
            if key.startswith(prefix):
                charts[key] = ["Multiline", [f"^{re.escape(f'{p}/{key}')}$" for p in (THETA_PREFIX, THETA_P_PREFIX)]]
        layout[THETA_CATEGORY.format(output=f"out{j}")] = charts
    return layout


def compliance_layout(num_sources: int) -> dict[str, dict[str, list[Any]]]:
    """The custom scalar chart of a run with several sources: Λ_k of each source k (Eq. 14) over the episodes."""
    tags = [f"^{re.escape(f'transfer/{SOURCE_COMPLIANCE_PREFIX}/{k}')}$" for k in range(num_sources)]
    return {TRANSFER_CATEGORY: {COMPLIANCE_CHART: ["Multiline", tags]}}


def start_dashboards(writer: SummaryWriter, cfg: DictConfig, task: Task, plan: TransferPlan) -> None:
    """What a fresh run writes once (a resume keeps it): HParams session, chart layout, config and plan text."""
    rule = plan.rule.name
    gamma = getattr(plan.rule, "gamma", 0.0 if rule in RULES_WITH_ZERO_GAMMA else None)
    hparams = run_hparams(cfg, approach_of(bool(plan.sources), rule), rule, gamma)
    layout = scalar_layout(len(plan.outputs), task.gp_input_dim, plan.outputs)
    if plan.several:  # the choice among several sources, and a chart of every Λ_k
        hparams.update(sources=len(plan.sources), select=plan.select)
        layout.update(compliance_layout(len(plan.sources)))
    if plan.samples != "none":  # source samples weighted by relevance, and how many at most
        hparams.update(samples=plan.samples, max_source_samples=plan.max_source_samples)
    write_session(writer, hparams)
    writer.add_custom_scalars(layout)
    write_run_text(writer, OmegaConf.to_yaml(cfg, resolve=True), plan.describe())
    writer.flush()


def write_run_text(writer: SummaryWriter, config_yaml: str, plan: str) -> None:
    """The resolved config (YAML, as a Markdown code block) and the transfer plan's description, at step 0."""
    writer.add_text(CONFIG_TAG, "".join(f"    {line}\n" for line in config_yaml.splitlines()), 0)
    writer.add_text(PLAN_TAG, plan, 0)
