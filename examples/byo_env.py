"""Bring your own env: a gymnasium env written here, registered, described to qtl as a task, and learned.

The env is a puck on a track with friction, pushed by a bounded force: it starts 1 m left of the origin, at
rest, and should be brought to the origin and held there. It follows none of qtl's conventions: its own reward
is a quadratic cost, it ends the episode when the puck leaves the track, and it says nothing of its start
distribution. The task below tells qtl what it needs: the saturating reward to learn with, the Gaussian start
x_0 ~ N(μ_0, Σ_0), the horizon and the success test (what a task YAML under ``configs/task/`` would say).

    .venv/bin/python examples/byo_env.py               # 1 random + 5 learned episodes
    .venv/bin/python examples/byo_env.py --tiny        # a seconds-long smoke run

The run goes to ``<out>`` (default ``outputs/examples/byo_env``), an ordinary qtl-train run directory;
running again reuses a finished run and resumes an interrupted one. Extra arguments are qtl-train overrides.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
from hydra import compose, initialize_config_module
from hydra.core.config_store import ConfigStore

from qtl.config import register_configs
from qtl.errors import UserError
from qtl.loop import run
from qtl.train import auto_resume

ENV_ID = "examples/PuckOnTrack-v0"


class PuckOnTrackEnv(gymnasium.Env):
    """A 1 kg puck on a 4 m track with viscous friction; the action is the force on it, in [−1, 1] N.

    State (x, v): position (m) and velocity (m/s). Euler steps of dt = 0.1 s: v' = v + dt (u − b v), x' = x + dt v'.
    Reward (its own, which qtl logs as ``env_return`` but does not learn with): −(x² + 0.1 u²).
    Start: x ~ N(−1, 0.05²), v ~ N(0, 0.05²). Terminated when the puck leaves the track, |x| > 2 m.
    """

    def __init__(self, friction: float = 0.5, dt: float = 0.1) -> None:
        self.friction, self.dt = friction, dt
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float64)  # 1-D Boxes, as qtl needs
        self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float64)
        self.state = np.zeros(2)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)  # seeds self.np_random: qtl resets each episode with its own seed
        self.state = np.array([-1.0, 0.0]) + 0.05 * self.np_random.standard_normal(2)
        return self.state.copy(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        u = float(np.clip(action[0], -1.0, 1.0))
        x, v = self.state
        v = v + self.dt * (u - self.friction * v)
        x = x + self.dt * v
        self.state = np.array([x, v])
        return self.state.copy(), -(x**2 + 0.1 * u**2), bool(abs(x) > 2.0), False, {}


# What qtl needs to know about the task, in the fields of a task YAML (docs/guide/byo-env.md lists them all).
TASK = {
    "name": "puck",
    "env": {"id": ENV_ID},          # any registered id; keys beside `id` are the env's constructor kwargs
    "horizon": 40,                  # 4 s per episode, and the prediction horizon of the policy search
    "angle_dims": [],               # no raw angles in the state
    "state_names": ["x (m)", "v (m/s)"],
    "start": {"mean": [-1.0, 0.0], "std": [0.05, 0.05]},  # the reset's distribution, N(μ_0, diag(σ_0²))
    "reward": {                     # r(x) = exp(−½ (x − x*)ᵀ W (x − x*) / width²): the puck at 0, speed left out
        "angle_dims": [],
        "target": [0.0, 0.0],
        "weight": [[1.0, 0.0], [0.0, 0.0]],
        "width": 0.5,
    },
    "policy_size": 20,              # basis functions of the RBF policy
    "success": {"threshold": 0.1, "last_steps": 10},  # within 0.1 m of the origin for the last 1 s
}
# The tests' tiny budget: 6 steps per episode, a handful of GP-fit and policy-search iterations.
TINY = ["task.horizon=6", "task.success.last_steps=2", "task.policy_size=4", "optimizer.max_iter=2",
        "optimizer.restarts=1", "model.restarts=1", "model.max_iter=3", "figure_every=0"]


def main() -> None:
    """Register the env and the task, learn it, print the returns."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=5, help="learned episodes, after 1 of random actions")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("outputs/examples/byo_env"), help="the run directory")
    parser.add_argument("--tiny", action="store_true", help="the tests' tiny budget (a smoke run, learns nothing)")
    args, extra = parser.parse_known_args()
    out = args.out.expanduser().resolve()
    logging.basicConfig(level=logging.INFO, format="%(message)s")  # the loop's one line per episode

    # 1. Register the env with gymnasium, as any env package does (qtl makes it by id).
    if ENV_ID not in gymnasium.registry:
        gymnasium.register(ENV_ID, entry_point=PuckOnTrackEnv)
    # 2. Register the task as an option of qtl-train's `task` group: `task=puck` then selects it.
    register_configs()
    ConfigStore.instance().store(group="task", name="puck", node=TASK)
    # 3. Compose the run's configuration: qtl-train's defaults, this task, the budget.
    with initialize_config_module("qtl.configs", version_base="1.3"):
        cfg = compose("train", overrides=["task=puck", f"seed={args.seed}", f"episodes={args.episodes}",
                                          *(TINY if args.tiny else []), *extra])
    # 4. Learn it: Algorithm 1 (PILCO), reusing or resuming a run of the same configuration in `out`.
    cfg = auto_resume(out, cfg)
    result = run(cfg, out, resume=cfg.resume is not None)

    print(f"\n{'episode':>7}  {'return':>8}  success")
    for episode, (ret, success) in enumerate(zip(result.returns, result.successes, strict=True)):
        print(f"{episode:>7}  {ret:>8.2f}  {'yes' if success else 'no'}")
    print(f"\nreturns of {result.output_dir}/metrics.csv (at most {cfg.task.horizon} per episode); "
          f"TensorBoard: tensorboard --logdir {result.output_dir}")


if __name__ == "__main__":
    try:
        main()
    except UserError as err:  # bad input, e.g. an --out that holds a run of another configuration: one line
        sys.exit(f"{Path(__file__).name}: {err}")
