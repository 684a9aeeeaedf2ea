"""Quickstart: PILCO learns the cart-pole swing-up through qtl's Python API, Algorithm 1 written out.

One episode of random actions; then, each episode, a GP dynamics model fitted to all the data so far, a
policy searched through moment-matching rollouts of that model, and one episode of the policy on the
cart-pole, whose return (the task's saturating reward, at most 50) is printed. Extra arguments are
qtl-train overrides, e.g. ``.venv/bin/python examples/quickstart.py episodes=3 task.env.pole_mass=1.0``.
``qtl.loop.run(cfg, out_dir)`` is the same loop with logging, checkpoints and transfer: what qtl-train runs.
"""

import functools
import sys

import numpy as np
import torch
from hydra import compose, initialize_config_module

from qtl.build import build
from qtl.config import register_configs
from qtl.data import TransitionDataset
from qtl.episodes import random_actor, run_episode

register_configs()
with initialize_config_module("qtl.configs", version_base="1.3"):
    cfg = compose("train", overrides=["task=cartpole", *sys.argv[1:]])  # qtl-train's config and defaults
parts = build(cfg)  # the task (env, reward, start distribution) and the components: GP, propagation, search
task, env, policy = parts.task, parts.task.make_env(), parts.initial_policy()
data = TransitionDataset(task.state_dim, task.action_dim, task.angle_dims)
episode = run_episode(env, task, random_actor(task, np.random.default_rng(cfg.seed)), seed=cfg.seed)
print(f"episode 0 (random actions): return {episode.rewards.sum():.2f}")
for i in range(1, cfg.episodes + 1):
    data.add_episode(episode.states, episode.actions)
    model = parts.fit_dynamics(data, torch.Generator().manual_seed(cfg.seed + i))  # GP of Δx on (x, u), θ by evidence
    rollouts = parts.make_propagator(model, policy, parts.reward, angle_dims=task.angle_dims)  # moment matching
    parts.search(policy, functools.partial(rollouts.expected_return, parts.start, task.horizon))  # ψ by L-BFGS
    episode = run_episode(env, task, parts.actor(policy), seed=cfg.seed + i)  # the policy on the real system
    print(f"episode {i}: return {episode.rewards.sum():.2f}, success {task.succeeded(episode.states)}")
