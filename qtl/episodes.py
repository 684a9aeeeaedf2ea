"""Episodes on the real system (Algorithm 1, lines 3 and 11): who acts, what is kept, how the model did on them."""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import gymnasium
import numpy as np
import torch

from qtl.constraints import Constraint
from qtl.data import TransitionDataset, gp_training_pairs
from qtl.errors import NonFiniteObjective
from qtl.features import AngleFeatures
from qtl.gaussian import Gaussian
from qtl.models import DynamicsGP
from qtl.policies import Policy
from qtl.propagation import Propagator
from qtl.recorder import trajectory_figure
from qtl.task import Task

if TYPE_CHECKING:
    from matplotlib.figure import Figure

log = logging.getLogger(__name__)

# An actor: the action `F` for a real observation `D`.
Actor = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class Episode:
    """One episode on the real system: states `T+1 x D`, actions `T x F`, the task's and the env's rewards `T`."""

    states: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray  # the task's saturating reward: what the learner is scored by
    env_rewards: np.ndarray  # what env.step returned, logged beside it
    terminated: bool = False  # the env ended the episode (``terminated``) after T steps

    @property
    def length(self) -> int:
        """Number of steps T."""
        return len(self.actions)


def run_episode(env: gymnasium.Env, task: Task, act: Actor, seed: int) -> Episode:
    """Apply ``act`` on the real system for at most H steps (Algorithm 1, lines 3 and 11).

    Rewards are the task's saturating reward of each successor state: the env's own when it
    exposes the same ``reward_spec``, else the configured ``task.reward`` of the observation; the
    env's own rewards are kept beside them. An episode the env ends (``terminated``) or truncates
    stops there. The env is reset with ``task.reset_options`` (None: the env's default reset).
    """
    obs, _ = env.reset(seed=seed, options=task.reset_options)
    states, actions, rewards, env_rewards = [obs], [], [], []
    terminated = False
    for _ in range(task.horizon):
        action = np.clip(act(obs), -task.action_bound, task.action_bound)
        obs, reward, terminated, truncated, _ = env.step(action.astype(env.action_space.dtype))
        states.append(obs)
        actions.append(action)
        rewards.append(reward if task.reward_from_env else task.reward(obs))
        env_rewards.append(reward)
        if terminated or truncated:
            break
    return Episode(np.asarray(states, dtype=float), np.asarray(actions, dtype=float), np.asarray(rewards, dtype=float),
                   np.asarray(env_rewards, dtype=float), bool(terminated))


def random_actor(task: Task, rng: np.random.Generator) -> Actor:
    """Actions uniform in the action bounds, whatever the state (Algorithm 1, line 3)."""
    return lambda _obs: rng.uniform(-task.action_bound, task.action_bound)


def policy_actor(
    policy: Policy, features: AngleFeatures, dtype: torch.dtype, device: torch.device | str = "cpu"
) -> Actor:
    """u = π(φ(x)) on a real observation (Algorithm 1, line 11); the action back on the CPU as numpy."""

    def act(obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return policy(features(torch.as_tensor(obs, dtype=dtype, device=device))).cpu().numpy()

    return act


def one_step_smse(model: DynamicsGP, episode: Episode, features: AngleFeatures, dtype: torch.dtype) -> float:
    """Model fit quality: one-step prediction error on an episode it has not seen, over target variance."""
    data = TransitionDataset(episode.states.shape[1], episode.actions.shape[1], features.angle_dims)
    data.add_episode(episode.states, episode.actions)
    inputs, targets = gp_training_pairs(data, features, dtype, model.train_x.device)
    targets = targets[:, list(model.outputs)]  # the state dimensions the model's outputs are
    mean, _ = model.predict(inputs)
    mse = ((mean - targets) ** 2).mean(0)
    return float((mse / model.train_y.var(0)).mean())


def prediction_figure(
    propagator: Propagator,
    start: Gaussian,
    horizon: int,
    real: Episode,
    title: str,
    state_names: Sequence[str] | None = None,
    constraints: Sequence[Constraint] = (),
) -> Figure | None:
    """The predicted state distribution of the policy over H steps against what the real system did.

    A real episode the env ended before the horizon is marked where it ended; the region beyond
    each of the task's ``constraints`` is shaded. None (with a warning) when the predicted rollout
    breaks down numerically.
    """
    try:
        with torch.no_grad():
            predicted = propagator.rollout(start, horizon).states  # (H+1) x D
    except (NonFiniteObjective, torch.linalg.LinAlgError) as err:
        log.info("no prediction figure for %s: the predicted rollout broke down (%s)", title, err)
        return None
    mean = predicted.mean.cpu().numpy()
    std = torch.diagonal(predicted.cov, dim1=-2, dim2=-1).clamp_min(0).sqrt().cpu().numpy()
    ended = real.length if real.length < horizon else None
    return trajectory_figure(mean, std, real.states, title, state_names=state_names, ended_at=ended,
                             ended_label="terminated" if real.terminated else "ended", constraints=constraints)
