"""Qualitative transfer on the cart-pole swing-up: learn a 0.5 kg pole, then transfer to a 2.0 kg one.

1. PILCO learns the 0.5 kg swing-up from scratch: the source task.
2. QTL-PILCO (Bayesian rule) learns the 2.0 kg target starting from the source's GP hyper-parameters θ_s
   and final policy ψ_s; PILCO learns the same target from scratch beside it, for comparison.
3. The two target learning curves are plotted in one PNG, and summarised in a table.

    .venv/bin/python examples/cartpole_transfer.py                    # 1 initial + 9 learned episodes per run
    .venv/bin/python examples/cartpole_transfer.py --episodes 3 --tiny   # a seconds-long smoke run

Runs go to ``<out>/source``, ``<out>/target_qtl_bayesian`` and ``<out>/target_pilco``: ordinary qtl-train run
directories (``metrics.csv``, checkpoints, TensorBoard events). Running the script again reuses finished runs
and resumes interrupted ones. Extra arguments are qtl-train overrides applied to every run.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from hydra import compose, initialize_config_module
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator
from omegaconf import DictConfig

from qtl.config import register_configs
from qtl.demo import summary_table
from qtl.errors import UserError
from qtl.loop import RunResult, run
from qtl.train import auto_resume

# The tiny budget of the tests: 6 steps per episode, a handful of GP-fit and policy-search iterations.
TINY = ["task.horizon=6", "task.success.last_steps=2", "task.policy_size=4", "optimizer.max_iter=2",
        "optimizer.restarts=1", "model.restarts=1", "model.max_iter=3", "figure_every=0"]
# How each target run is drawn: QTL wide and solid, PILCO thin and dashed over it, so both show where they coincide.
STYLES = {
    "QTL-PILCO, Bayesian (θ_s, ψ_s)": {"color": "#d62728", "linestyle": "-", "linewidth": 3.5, "marker": "o"},
    "PILCO from scratch": {"color": "#1f77b4", "linestyle": "--", "linewidth": 1.5, "marker": "s", "markersize": 4},
}


def config(overrides: list[str]) -> DictConfig:
    """qtl-train's configuration (``configs/train.yaml`` and its defaults) with ``overrides``, as the CLI has it."""
    with initialize_config_module("qtl.configs", version_base="1.3"):
        return compose("train", overrides=overrides)


def learn(overrides: list[str], run_dir: Path) -> RunResult:
    """Algorithm 1 on the task of ``overrides`` in ``run_dir``; a finished run there is reused, a cut one resumed."""
    cfg = auto_resume(run_dir, config(overrides))  # resume=run_dir if it holds this config's run (another: an error)
    return run(cfg, run_dir, resume=cfg.resume is not None)


def plot(curves: dict[str, RunResult], path: Path, title: str) -> None:
    """The target runs' returns per episode, successful episodes marked, in one PNG."""
    fig = Figure(figsize=(7, 4))  # no pyplot: no window, whatever the machine's display
    ax = fig.subplots()
    for name, result in curves.items():
        episodes = range(len(result.returns))
        ax.plot(episodes, result.returns, label=name, **STYLES[name])
        won = [e for e in episodes if result.successes[e]]
        ax.plot(won, [result.returns[e] for e in won], "*", color=STYLES[name]["color"], markersize=16)
    ax.set(xlabel="episode (0: the initial one)", ylabel="return (saturating reward, summed)", title=title)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.legend(title="★: a successful episode")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def main() -> None:
    """Source run, the two target runs, the figure and the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=9, help="learned episodes per run, after 1 initial one")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--mass", type=float, default=2.0, help="the target's pole mass in kg (the source's: 0.5)")
    parser.add_argument("--out", type=Path, default=Path("outputs/examples/cartpole_transfer"), help="where runs go")
    parser.add_argument("--tiny", action="store_true", help="the tests' tiny budget (a smoke run, learns nothing)")
    args, extra = parser.parse_known_args()
    out = args.out.expanduser().resolve()
    logging.basicConfig(level=logging.INFO, format="%(message)s")  # the loop's one line per episode
    register_configs()  # qtl's config schema, which qtl-train registers at import
    common = ["task=cartpole", f"seed={args.seed}", f"episodes={args.episodes}", *(TINY if args.tiny else []), *extra]

    # 1. The source: PILCO from scratch on the 0.5 kg pole (the cart-pole task's default mass).
    print(f"[1/3] source: PILCO on the 0.5 kg cart-pole -> {out / 'source'}", flush=True)
    learn(common, out / "source")

    # 2. The target, twice: with transfer from the source run, and from scratch.
    target = [*common, f"task.env.pole_mass={args.mass}"]
    runs = {  # approach=qtl_bayesian: rule=bayesian, transfer.hyperparameters=true (θ_s), transfer.policy=true (ψ_s)
        "QTL-PILCO, Bayesian (θ_s, ψ_s)": ([*target, "approach=qtl_bayesian", f"transfer.source={out / 'source'}"],
                                           out / "target_qtl_bayesian"),
        "PILCO from scratch": (target, out / "target_pilco"),
    }
    curves = {}
    for step, (name, (overrides, run_dir)) in enumerate(runs.items(), start=2):
        print(f"[{step}/3] target {args.mass} kg: {name} -> {run_dir}", flush=True)
        curves[name] = learn(overrides, run_dir)

    # 3. The two target learning curves in one figure, and the summary of all three runs.
    figure = out / "target_learning_curves.png"
    plot(curves, figure, f"cart-pole swing-up, {args.mass} kg pole (seed {args.seed})")
    print("\n" + summary_table({"source 0.5 kg, PILCO": out / "source",
                                **{f"target {args.mass} kg, {name}": run_dir for name, (_, run_dir) in runs.items()}}))
    print(f"\nlearning curves: {figure}\nTensorBoard: tensorboard --logdir {out}")


if __name__ == "__main__":
    try:
        main()
    except UserError as err:  # bad input, e.g. an --out that holds a run of another configuration: one line
        sys.exit(f"{Path(__file__).name}: {err}")
