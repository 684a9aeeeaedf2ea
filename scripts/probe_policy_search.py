"""Re-run one policy search on a finished run's data, with other settings, and try the result on the real system.

A diagnostic for a run that stopped improving: the model is refitted on the run's data (its last checkpoint
or ``--checkpoint``) with the run's model settings as the run's next episode would fit it (warm-started from
the checkpoint's fit, with the run's random stream, cold restarts from the transfer plan's start, and θ set by
the run's updating rule from its checkpointed state: the model the run's next search would use), the search
starts from the run's last policy (or from a fresh ψ_0 with ``--fresh``) and uses the run's config with the
given Hydra overrides (e.g. ``propagation=moment_matching``, ``optimizer=adam optimizer.steps=400``). Printed:
the predicted return before and after, each search run's best value, evaluations, wall time, and the returns
of ``--episodes`` real episodes of the found policy (their success by the task's test).

    .venv/bin/python scripts/probe_policy_search.py RUN_DIR [--checkpoint PATH] [--fresh] [--episodes 3]
        [--threads 1] [--seed 0] [OVERRIDE ...]
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from pathlib import Path

import benchlib
import torch
from omegaconf import DictConfig, OmegaConf

from qtl.build import Parts, build, transfer_plan
from qtl.checkpoint import latest_checkpoint, load_checkpoint
from qtl.config import GROUP_SCHEMAS, typed_groups
from qtl.data import TransitionDataset
from qtl.episodes import run_episode
from qtl.loop import MODEL_STREAM
from qtl.models import DynamicsGP
from qtl.models.warm_start import PreviousFit
from qtl.seeding import torch_generator

EVALUATION_SEED = 100  # real episodes use env seeds 100, 101, ...: not the run's own


def with_overrides(cfg: DictConfig, overrides: list[str]) -> DictConfig:
    """The run's config with ``group=option`` (any config group's schema) and then ``key=value`` overrides.

    A leading ``+`` is dropped (the typed groups hold every key); a key outside the config is refused, not ignored.
    """
    rest = []
    for override in overrides:
        override = override.removeprefix("+")  # Hydra's "add a key": the typed groups take it as a plain key
        key, _, value = override.partition("=")
        if key.split(".", 1)[0] not in cfg:
            raise SystemExit(f"unknown override {override!r}: {key.split('.', 1)[0]!r} is not in the run's config")
        if key in GROUP_SCHEMAS:  # `group=option` replaces the whole node, as on the CLI
            if value not in GROUP_SCHEMAS[key]:
                raise SystemExit(f"unknown {key}={value!r}: choose one of {sorted(GROUP_SCHEMAS[key])}")
            cfg[key] = OmegaConf.structured(GROUP_SCHEMAS[key][value])
        else:
            rest.append(override)
    return OmegaConf.merge(cfg, OmegaConf.from_dotlist(rest))


def refitted(checkpoint: dict, overrides: list[str]) -> tuple[Parts, TransitionDataset, DynamicsGP]:
    """The checkpoint's config with ``overrides`` built, its data, and the model the run's next episode would search
    on (Algorithm 1, lines 12-13): θ_p fitted warm from the checkpoint's fit (``model.warm_start``) with the run's
    own random stream and the transfer plan's cold start, then θ = the updating rule's θ_i from the checkpointed
    rule state (Eqs. 6-12; θ_p itself for PILCO). Loads the run's source run, where it has one."""
    cfg = with_overrides(typed_groups(OmegaConf.create(checkpoint["config"])), overrides)
    parts = build(cfg)
    data = TransitionDataset.from_state(checkpoint["dataset"], parts.task.angle_dims)
    plan = transfer_plan(cfg, parts)
    if "transfer" in checkpoint:  # checkpoints of runs made before transfer existed are PILCO runs
        plan.load_state_dict(checkpoint["transfer"])
    generator = torch_generator(cfg.seed, checkpoint["episode"] + 1, MODEL_STREAM)
    model = parts.fit_dynamics(data, generator, start=plan.fit_start(), previous=PreviousFit.of_checkpoint(checkpoint))
    theta_p = model.hyperparameters
    theta = plan.update(theta_p, len(data), plan.compliance(model))
    if theta is not theta_p:
        model.hyperparameters = theta
    return parts, data, model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--checkpoint", type=Path, help="default: the run's latest")
    parser.add_argument("--fresh", action="store_true", help="start from a fresh ψ_0, not the run's policy")
    parser.add_argument("--episodes", type=int, default=3, help="real episodes of the found policy")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0, help="of the search's restarts")
    args, overrides = parser.parse_known_args()
    torch.set_num_threads(args.threads)

    checkpoint = load_checkpoint(args.checkpoint or latest_checkpoint(args.run_dir))
    parts, data, model = refitted(checkpoint, overrides)
    task, start = parts.task, parts.start
    policy = parts.initial_policy()
    if not args.fresh:
        policy.load_state_dict(checkpoint["policy"])
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
    print(json.dumps({"run": benchlib.display_path(args.run_dir), "episode": checkpoint["episode"], "n": len(data),
                      "overrides": overrides, "fresh": args.fresh, "predicted_before": round(before, 2),
                      "predicted_after": round(found.value, 2),
                      "predicted_after_task_reward": round(after_task, 2),
                      "run_values": [round(v, 2) for v in found.run_values],
                      "evaluations": found.evaluations, "search_s": round(seconds, 1), "real": real}))


if __name__ == "__main__":
    main()
