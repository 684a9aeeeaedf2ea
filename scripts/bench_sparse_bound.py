"""Benchmark the sparse GP evidence: the collapsed bound in closed form against GPyTorch's, in one run.

For each case, the sparse GP the sweeps fit (E = 4 outputs, m = 300 inducing inputs, δ = 1e-6 α² on K_mm):

- synthetic: n points of a smooth 6-D function with noise (as ``bench_gp.py``), PILCO's heuristic θ, Z drawn
  from the data;
- run: a run's checkpoint (default: the cart-pole sweep's source seed 0 after its last episode), its data with
  the θ and learned Z of its last fit (inducing inputs that crowd the data: K_mm near singular).

Timed, alternately and in this process's CPU time on one torch thread (the work, whatever else shares the
cores): one evaluation of the objective with its gradient by ``SparseDynamicsGP.log_evidence`` (closed form)
and by ``gpytorch_log_evidence`` (GPyTorch's ``ExactMarginalLogLikelihood``, the path before), with the largest
relative differences of value and gradient; then, for the ``--fit`` cases, one whole L-BFGS run of the fit
(``_optimise``, the default budget) from the same θ and Z by each: CPU time, evaluations and the objective
reached. Writes ``docs/bench/sparse_bound.json`` and its section of ``docs/benchmarks.md``.

    .venv/bin/python scripts/bench_sparse_bound.py [--sizes 400 800 1250 2000] [--fit synthetic-1250 run]
        [--checkpoint PATH|none] [--inducing 300] [--repeats 7] [--threads 1]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import torch

from qtl.bench import (
    ROOT,
    command_line,
    commit,
    display_path,
    machine,
    markdown_table,
    today,
    write_results,
    write_section,
)
from qtl.data import TransitionDataset, gp_training_pairs
from qtl.features import AngleFeatures
from qtl.models import GPHyperparameters, SparseDynamicsGP
from qtl.models.gp_evidence import DEFAULT_MAX_ITER

INPUT_DIM, OUTPUTS, INDUCING = 6, 4, 300
NOISE_STD = 0.05
DEFAULT_CHECKPOINT = ROOT / "docs" / "experiments" / "cartpole" / "source" / "seed_0" / "checkpoints" \
    / "episode_0024.pt"
DEFAULT_OUTPUT = ROOT / "docs" / "bench" / "sparse_bound.json"
SECTION = "bench_sparse_bound"


def synthetic(n: int, seed: int, inducing: int = INDUCING) -> SparseDynamicsGP:
    """n points of sin(x W / 2) + noise, x in [-2, 2]^6, at PILCO's heuristic θ with ``inducing`` inputs drawn."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.rand(n, INPUT_DIM, generator=gen, dtype=torch.float64) * 4 - 2
    w = torch.randn(INPUT_DIM, OUTPUTS, generator=gen, dtype=torch.float64)
    y = torch.sin(x @ w / 2) + NOISE_STD * torch.randn(n, OUTPUTS, generator=gen, dtype=torch.float64)
    return SparseDynamicsGP(x, y, num_inducing=inducing, generator=gen)


def from_checkpoint(path: Path) -> SparseDynamicsGP:
    """A run's data at the θ and inducing inputs of its last fit."""
    state = torch.load(path, map_location="cpu", weights_only=False)
    data = state["dataset"]
    dataset = TransitionDataset(data["state_dim"], data["action_dim"], data["angle_dims"])
    for states, actions in zip(data["states"], data["actions"], strict=True):
        dataset.add_episode(states.numpy(), actions.numpy())
    inputs, targets = gp_training_pairs(dataset, AngleFeatures(data["state_dim"], tuple(data["angle_dims"])),
                                        torch.float64)
    fit = state["previous_fit"]
    theta = GPHyperparameters(**{name: torch.as_tensor(value) for name, value in fit["theta"].items()})
    return SparseDynamicsGP(inputs, targets, theta, inducing_points=fit["inducing"])


def evaluation(model: SparseDynamicsGP, path: str) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """The objective `E` and its gradient in every trained parameter, by ``path``."""
    params = [param for param in model.parameters() if param.requires_grad]
    value = model.log_evidence() if path == "closed_form" else model.gpytorch_log_evidence()
    return value.detach(), list(torch.autograd.grad(value.sum(), params))


def max_relative(got: torch.Tensor, want: torch.Tensor) -> float:
    """max |got − want| / max |want|."""
    return float((got - want).abs().max() / want.abs().max())


def one_fit(model: SparseDynamicsGP, path: str) -> dict[str, float]:
    """One L-BFGS run of the fit (the default budget) by ``path``: CPU s, evaluations, objective per point."""
    evaluate = model.log_evidence if path == "closed_form" else model.gpytorch_log_evidence
    calls = {"count": 0}

    def counted() -> torch.Tensor:
        calls["count"] += 1
        return evaluate()

    model.log_evidence = counted  # the instance attribute shadows the method for this run
    try:
        cpu = time.process_time()
        value = model._optimise(DEFAULT_MAX_ITER)
        seconds = time.process_time() - cpu
    finally:
        del model.log_evidence
    return {"cpu_s": seconds, "evaluations": calls["count"], "objective": float(value.mean())}


def measure(name: str, model: SparseDynamicsGP, repeats: int, fit: bool) -> dict[str, Any]:
    """Both paths on one model: eval + gradient alternately, agreement, and (``fit``) a whole L-BFGS run each."""
    model.train()
    times: dict[str, list[float]] = {"gpytorch": [], "closed_form": []}
    for index in range(repeats + 1):  # the first of each is a warm-up
        for path in times:
            cpu = time.process_time()
            evaluation(model, path)
            if index:
                times[path].append(time.process_time() - cpu)
    value, grads = evaluation(model, "closed_form")
    ref_value, ref_grads = evaluation(model, "gpytorch")
    old_s, new_s = statistics.median(times["gpytorch"]), statistics.median(times["closed_form"])
    row: dict[str, Any] = {
        "case": name, "n": int(model.train_x.shape[0]), "inducing": int(model.inducing_points.shape[0]),
        "outputs": model.num_outputs, "gpytorch_s": old_s, "closed_form_s": new_s, "ratio": new_s / old_s,
        "times": times, "value_rel_diff": max_relative(value, ref_value),
        "grad_rel_diff": max(max_relative(g, r) for g, r in zip(grads, ref_grads, strict=True)),
    }
    if fit:
        start_theta, start_z = model.hyperparameters, model.inducing_points.clone()
        for path in ("gpytorch", "closed_form"):
            model.hyperparameters = start_theta
            with torch.no_grad():
                model.covar_module.inducing_points.copy_(start_z)
            model.train()
            row[f"fit_{path}"] = one_fit(model, path)
        row["fit_ratio"] = row["fit_closed_form"]["cpu_s"] / row["fit_gpytorch"]["cpu_s"]
    return row


def fit_cells(row: dict[str, Any]) -> list[str]:
    """A row's fit columns: each path's CPU s, evaluations and objective, and their ratio (dashes without a fit)."""
    if "fit_ratio" not in row:
        return ["—", "—", "—"]
    paths = [row["fit_gpytorch"], row["fit_closed_form"]]
    return [*(f"{f['cpu_s']:.1f}, {f['evaluations']}, {f['objective']:.4f}" for f in paths), f"{row['fit_ratio']:.2f}×"]


def markdown(rows: list[dict[str, Any]], info: dict[str, Any]) -> str:
    """The section of docs/benchmarks.md."""
    lines = [
        "## Sparse GP evidence: the collapsed bound in closed form against GPyTorch's",
        "",
        f"`{info['command']}` at commit {info['commit']} — {info['date']}, {info['machine']['cpu']} "
        f"({info['machine']['cores']} cores), {info['threads']} torch thread(s), torch {info['machine']['torch']}; "
        f"1-min load average {info['load_before']:.2f} before, {info['load_after']:.2f} after. "
        f"Results: `{info['output']}`.",
        "",
        "One evaluation of the sparse GP's objective (Titsias' bound + log priors, per point) with its gradient in "
        "every trained parameter (θ and the inducing inputs Z), by GPyTorch's `ExactMarginalLogLikelihood` (the path "
        "before) and by `qtl.models.collapsed_bound` (the default), timed alternately: medians of "
        f"{info['repeats']} after a warm-up, this process's CPU time. Ratio = closed form / GPyTorch, measured in "
        "the same run. Max rel. diff: closed form against GPyTorch, value and gradient. Fit: one whole L-BFGS run "
        f"(at most {DEFAULT_MAX_ITER} iterations) from the same θ and Z by each path.",
        "",
        markdown_table([[r["case"], r["n"], r["inducing"], f"{r['gpytorch_s']:.3f}", f"{r['closed_form_s']:.3f}",
                         f"{r['ratio']:.2f}×", f"{r['value_rel_diff']:.1e}, {r['grad_rel_diff']:.1e}", *fit_cells(r)]
                        for r in rows],
                       ["case", "n", "m", "GPyTorch (CPU s)", "closed form (CPU s)", "ratio",
                        "rel. diff: value, gradient", "fit: GPyTorch (CPU s, evals, objective)", "fit: closed form",
                        "fit ratio"], "lrrrrrlllr"),
    ]
    return "\n".join(lines)


def main() -> None:
    """Time both paths on each case; write the JSON and (unless ``--no-docs``) the section."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="*", default=[400, 800, 1250, 2000])
    parser.add_argument("--checkpoint", default=str(DEFAULT_CHECKPOINT),
                        help="a run's episode checkpoint (the 'run' case; 'none': no such case)")
    parser.add_argument("--inducing", type=int, default=INDUCING, help="inducing inputs of the synthetic cases")
    parser.add_argument("--fit", nargs="*", default=["synthetic-1250", "run"],
                        help="the cases that also get a whole L-BFGS run by each path")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (a sweep job uses one)")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    parser.add_argument("--no-docs", action="store_true")
    args = parser.parse_args()
    checkpoint = None if args.checkpoint == "none" else Path(args.checkpoint)
    if checkpoint is not None and not checkpoint.is_file():
        parser.error(f"--checkpoint {checkpoint} does not exist: give a run's checkpoints/episode_NNNN.pt, or none")
    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()[0]
    cases = [(f"synthetic-{n}", lambda n=n: synthetic(n, args.seed, args.inducing)) for n in args.sizes]
    if checkpoint is not None:
        cases.append(("run", lambda: from_checkpoint(checkpoint)))
    rows = []
    for name, make in cases:
        rows.append(measure(name, make(), args.repeats, name in args.fit))
        print({k: v for k, v in rows[-1].items() if k != "times"}, file=sys.stderr, flush=True)
    output = args.output.resolve()
    info = {"date": today(), "command": command_line(), "commit": commit(),
            "machine": machine(), "threads": args.threads, "repeats": args.repeats, "seed": args.seed,
            "checkpoint": None if checkpoint is None else display_path(checkpoint.resolve()),
            "load_before": load_before, "load_after": os.getloadavg()[0], "output": display_path(output)}
    write_results(output, info, rows)
    section = markdown(rows, info)
    if not args.no_docs:
        write_section(SECTION, section)
    print(section)


if __name__ == "__main__":
    main()
