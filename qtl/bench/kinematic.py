"""Full-state against kinematic moment matching (issue 63): ``propagation.integration`` delta vs speed, same data.

Both rows of a comparison share the data, the fitted model and ψ_0; only the step differs: ``delta`` (the GP on
every output, x + Δ) or ``speed`` (the GP on the non-position outputs, positions integrated from their velocities
with the task's ``kinematics.weight`` w: q + T q̇ + w T Δq̇).
The aircraft row is one batched search round of the full-scale preset's stage (``experiment=aircraft_source``,
the sparse GP with ``model.inducing`` inputs once the data pass ``model.sparse_above``), as ``bench_scale.py``
measures it, under both steps in one process.
"""

from __future__ import annotations

import copy
import time
from typing import Any

from omegaconf import DictConfig, OmegaConf

from qtl.bench.cells import markdown_table
from qtl.bench.scale import compose_stage, model_facts, stage_model
from qtl.bench.search import batched_rollout_grad
from qtl.build import build

INTEGRATIONS = ("delta", "speed")
AIRCRAFT_PRESET = "aircraft_source"
DESCRIPTION = (
    "Full-state against kinematic moment matching (`propagation.integration=delta|speed`, issue 63): the same data, "
    "model and ψ_0 in both rows; `speed` evaluates the GP on the non-position outputs only (E' of E, E'(E'+1)/2 "
    "output pairs instead of E(E+1)/2) and integrates the positions by the trapezoid rule. Cart-pole: one policy "
    "search and one rollout + gradient with the loop's settings, each row in its own subprocess. Aircraft: one "
    "batched search round (the R restarts' rollout + gradient at once) of the full-scale preset's stage, through "
    "the sparse GP it fits once the data pass `model.sparse_above`. Ratio: delta's time over speed's (above 1: "
    "speed is faster)."
)


def with_integration(cfg: DictConfig, integration: str) -> DictConfig:
    """A copy of ``cfg`` with ``propagation.integration`` set (``speed`` uses the kinematics its task declares)."""
    cfg = copy.deepcopy(cfg)
    cfg.propagation.integration = integration
    return cfg


def aircraft_rounds(overrides: list[str], seed: int, repeats: int) -> dict[str, Any]:
    """The aircraft stage's model (fitted once) and one batched search round under each step: median times (s)."""
    cfg = compose_stage(AIRCRAFT_PRESET, overrides)
    parts, model, n, fit_s = stage_model(cfg, seed)
    policy = parts.initial_policy()
    result: dict[str, Any] = {"task": parts.task.name, "n": n, **model_facts(model), "fit_s": fit_s,
                              "state_dim": parts.task.state_dim, "horizon": parts.task.horizon}
    for integration in INTEGRATIONS:
        stage = build(with_integration(cfg, integration))
        tic = time.perf_counter()
        measured = batched_rollout_grad(stage, model, policy, seed, repeats)
        result[integration] = {"round_s": measured["batched_rollout_grad_s_median"],
                               "restarts": measured["batched_restarts"], "wall_s": time.perf_counter() - tic}
    result["round_ratio"] = result["delta"]["round_s"] / result["speed"]["round_s"]
    result["kinematics"] = OmegaConf.to_container(with_integration(cfg, "speed").task.kinematics)
    return result


def ratio(rows: list[dict[str, Any]], n: int, key: str) -> float | None:
    """delta's ``key`` over speed's at ``n`` (None where either was not measured)."""
    by = {r.get("integration"): r for r in rows if r["n"] == n and "error" not in r}
    if key in by.get("delta", {}) and key in by.get("speed", {}):
        return by["delta"][key] / by["speed"][key]
    return None


def markdown(rows: list[dict[str, Any]], aircraft: dict[str, Any] | None) -> list[str]:
    """The comparison's tables: cart-pole searches per n, then the aircraft round."""
    lines = ["### Full-state vs kinematic moment matching", "", DESCRIPTION, ""]
    cells, errors = [], []
    for r in rows:
        if "error" in r:
            errors.append(f"{len(errors) + 1}. n = {r['n']}, {r['integration']}: `{r['error']}`")
        search, rollout = ratio(rows, r["n"], "search_s"), ratio(rows, r["n"], "rollout_grad_s_median")
        cells.append([r["n"], r["integration"], _s(r.get("search_s")), r.get("evaluations", "—"),
                      _s(r.get("rollout_grad_s_median"), 3),
                      f"{r['value_found']:.4g}" if "value_found" in r else "—",
                      f"{search:.2f}" if search and r["integration"] == "speed" else "",
                      f"{rollout:.2f}" if rollout and r["integration"] == "speed" else ""])
    if cells:
        lines.append(markdown_table(cells, ["n", "integration", "policy search (s)", "evaluations",
                                            "rollout + gradient (s)", "predicted return", "search ratio",
                                            "rollout ratio"], "rlrrrrrr"))
    if aircraft is not None:
        if "error" in aircraft:
            errors.append(f"{len(errors) + 1}. aircraft: `{aircraft['error']}`")
        else:
            lines += ["", f"Aircraft ({aircraft['task']}, n = {aircraft['n']}, {aircraft['model']}"
                          f"{', m = ' + str(aircraft['inducing']) if aircraft['inducing'] else ''}, "
                          f"H = {aircraft['horizon']}, R = {aircraft['delta']['restarts']} restarts): one batched "
                          f"round {aircraft['delta']['round_s']:.2f} s (delta) vs {aircraft['speed']['round_s']:.2f} s "
                          f"(speed), ratio {aircraft['round_ratio']:.2f}."]
    if errors:
        lines += ["", "Errors:", "", *errors]
    return lines


def _s(value: float | None, digits: int = 2) -> str:
    """Seconds for the table, or a dash."""
    return "—" if value is None else f"{value:.{digits}f}"
