"""Re-run one policy search on a finished run's data, with other settings, and try the result on the real system.

A diagnostic for a run that stopped improving: the model is refitted on the run's data (its last checkpoint
or ``--checkpoint``) with the run's model settings as the run's next episode would fit it (warm-started from
the checkpoint's fit, with the run's random stream, cold restarts from the transfer plan's start, and θ set by
the run's updating rule from its checkpointed state: the model the run's next search would use), the search
starts from the run's last policy (or from a fresh ψ_0 with ``--fresh``) and uses the run's config with the
given Hydra overrides (e.g. ``propagation=moment_matching``, ``optimizer=adam optimizer.steps=400``). Printed:
the predicted return before and after, each search run's best value, evaluations, wall time, and the returns
of ``--episodes`` real episodes of the found policy (their success by the task's test).

    .venv/bin/python scripts/research/probe_policy_search.py RUN_DIR [--checkpoint PATH] [--fresh] [--episodes 3]
        [--threads 1] [--seed 0] [OVERRIDE ...]
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from pathlib import Path

import torch

from qtl.bench import display_path
from qtl.bench.refit import loaded, refitted
from qtl.episodes import run_episode

EVALUATION_SEED = 100  # real episodes use env seeds 100, 101, ...: not the run's own


def main() -> None:
    """Refit the run's model, search again with the overrides, try the found policy on the real system."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--checkpoint", type=Path, help="default: the run's latest")
    parser.add_argument("--fresh", action="store_true", help="start from a fresh ψ_0, not the run's policy")
    parser.add_argument("--episodes", type=int, default=3, help="real episodes of the found policy")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0, help="of the search's restarts")
    args, overrides = parser.parse_known_args()
    torch.set_num_threads(args.threads)

    run = loaded(args.run_dir, args.checkpoint, overrides)
    data, model = refitted(run)
    parts = run.parts
    task, start = parts.task, parts.start
    policy = parts.initial_policy() if args.fresh else run.policy()
    propagator = parts.make_propagator(model, policy, parts.reward, angle_dims=task.angle_dims)
    with torch.no_grad():
        before = float(propagator.expected_return(start, task.horizon))
    tic = time.perf_counter()
    found = parts.search(policy, functools.partial(propagator.expected_return, start, task.horizon),
                   generator=torch.Generator().manual_seed(args.seed))
    seconds = time.perf_counter() - tic
    with torch.no_grad():  # under the task's reward (the search's may be wider)
        after_task = float(propagator.rollout(start, task.horizon).value)
    env = task.make_env()
    real = []
    for k in range(args.episodes):
        episode = run_episode(env, task, parts.actor(policy), EVALUATION_SEED + k)
        real.append({"return": round(float(episode.rewards.sum()), 2), "success": bool(task.succeeded(episode.states))})
    env.close()
    print(json.dumps({"run": display_path(args.run_dir), "episode": run.episode, "n": len(data),
                      "overrides": overrides, "fresh": args.fresh, "predicted_before": round(before, 2),
                      "predicted_after": round(found.value, 2),
                      "predicted_after_task_reward": round(after_task, 2),
                      "run_values": [round(v, 2) for v in found.run_values],
                      "evaluations": found.evaluations, "search_s": round(seconds, 1), "real": real}))


if __name__ == "__main__":
    main()
