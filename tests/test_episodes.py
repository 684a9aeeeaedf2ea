"""Episodes on the real system: bounded, reproducible by seed, the policy's actions, the model's one-step error."""

from __future__ import annotations

import logging
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from matplotlib.figure import Figure

from qtl.build import Parts, build
from qtl.data import TransitionDataset, gp_training_pairs
from qtl.episodes import Episode, one_step_smse, policy_actor, prediction_figure, random_actor, run_episode
from qtl.gaussian import Gaussian
from qtl.models import DynamicsGP
from qtl.task import Task
from tests.helpers import tiny_config
from tests.toy_envs import register_spinner, spinner_task


@pytest.fixture(scope="module")
def parts() -> Parts:
    """The tiny cart-pole task (horizon 8) and its parts."""
    return build(tiny_config())


def random_episode(parts: Parts, seed: int, action_seed: int = 0) -> Episode:
    env = parts.task.make_env()
    try:
        return run_episode(env, parts.task, random_actor(parts.task, np.random.default_rng(action_seed)), seed)
    finally:
        env.close()


def test_random_episode_has_the_documented_shapes_and_bounded_actions(parts):
    task = parts.task
    episode = random_episode(parts, seed=0)
    steps = len(episode.rewards)
    assert steps == task.horizon
    assert episode.states.shape == (steps + 1, task.state_dim) and episode.actions.shape == (steps, task.action_dim)
    assert np.all(np.abs(episode.actions) <= task.action_bound)
    assert np.all((episode.rewards >= 0) & (episode.rewards <= 1))  # the saturating reward


def test_same_seeds_same_episode_other_env_seed_other_start(parts):
    a, b, c = random_episode(parts, 1), random_episode(parts, 1), random_episode(parts, 2)
    np.testing.assert_array_equal(a.states, b.states)
    np.testing.assert_array_equal(a.actions, b.actions)
    assert not np.array_equal(a.states[0], c.states[0])


def test_actions_outside_the_bounds_are_clipped(parts):
    env = parts.task.make_env()
    episode = run_episode(env, parts.task, lambda obs: np.full(parts.task.action_dim, 1e6), seed=0)
    env.close()
    np.testing.assert_array_equal(episode.actions, np.broadcast_to(parts.task.action_bound, episode.actions.shape))


def test_policy_actor_applies_the_policy_to_the_features(parts):
    policy = parts.initial_policy()
    act = policy_actor(policy, parts.features, parts.dtype)
    obs = np.array([0.1, -0.2, 3.0, 0.5])
    with torch.no_grad():
        expected = policy(parts.features(torch.as_tensor(obs))).numpy()
    np.testing.assert_array_equal(act(obs), expected)
    np.testing.assert_array_equal(parts.actor(policy)(obs), expected)


def test_one_step_smse_is_the_mean_squared_error_over_the_targets_variance(parts):
    seen, unseen = random_episode(parts, 3, 3), random_episode(parts, 4, 4)
    data = TransitionDataset(parts.task.state_dim, parts.task.action_dim, parts.task.angle_dims)
    data.add_episode(seen.states, seen.actions)
    model = DynamicsGP(*gp_training_pairs(data, parts.features, parts.dtype))
    test = TransitionDataset(parts.task.state_dim, parts.task.action_dim, parts.task.angle_dims)
    test.add_episode(unseen.states, unseen.actions)
    inputs, targets = gp_training_pairs(test, parts.features, parts.dtype)
    mean, _ = model.predict(inputs)
    per_output = ((mean - targets) ** 2).mean(0) / model.train_y.var(0)
    assert one_step_smse(model, unseen, parts.features, parts.dtype) == pytest.approx(float(per_output.mean()))
    # On its own training tuples the GP is far better than on a new episode.
    assert one_step_smse(model, seen, parts.features, parts.dtype) < one_step_smse(model, unseen, parts.features,
                                                                                   parts.dtype)


class _BrokenPropagator:
    """A propagator whose rollout breaks down numerically."""

    def rollout(self, start, horizon):
        raise torch.linalg.LinAlgError("not positive definite")


def test_prediction_figure_has_a_panel_per_state_or_says_why_not_when_the_rollout_breaks(parts, caplog):
    real = random_episode(parts, 5)
    data = TransitionDataset(parts.task.state_dim, parts.task.action_dim, parts.task.angle_dims)
    data.add_episode(real.states, real.actions)
    model = DynamicsGP(*gp_training_pairs(data, parts.features, parts.dtype))
    propagator = parts.make_propagator(model, parts.initial_policy(), parts.reward, angle_dims=parts.task.angle_dims)
    figure = prediction_figure(propagator, parts.start, parts.task.horizon, real, "episode 1", parts.task.state_names)
    assert isinstance(figure, Figure) and len(figure.axes) >= parts.task.state_dim
    with caplog.at_level(logging.INFO, logger="qtl.episodes"):
        assert prediction_figure(_BrokenPropagator(), parts.start, 8, real, "episode 2") is None
    assert "no prediction figure for episode 2: the predicted rollout broke down" in caplog.text


@pytest.fixture(scope="module")
def spinner() -> Task:
    """The test spinner as a user's task: wrapped θ, a short track (early termination), its own reward."""
    return Task.from_config(spinner_task(env={"id": register_spinner(), "track": 0.6}, reset_options={"angle": 3.0}))


def test_an_episode_the_env_ends_stops_there_and_keeps_both_rewards(spinner):
    env = spinner.make_env()
    try:
        episode = run_episode(env, spinner, lambda obs: np.ones(1), seed=2)  # p grows 0.5 a step: off at step 2
        assert env.unwrapped.last_options == {"angle": 3.0}  # task.reset_options reached env.reset
        with spinner.make_env() as again:
            x0, _ = again.reset(seed=2, options={"angle": 3.0})
            expected = [again.step(np.ones(1))[1] for _ in range(2)]
    finally:
        env.close()
    assert episode.terminated and episode.length == 2 < spinner.horizon
    assert episode.states.shape == (3, 3) and episode.actions.shape == (2, 1)
    np.testing.assert_array_equal(episode.states[0], x0)
    np.testing.assert_array_equal(episode.env_rewards, expected)  # what env.step returned
    np.testing.assert_array_equal(episode.rewards, [spinner.reward(s) for s in episode.states[1:]])  # the task's
    assert np.all(episode.env_rewards < 0) and np.all((episode.rewards >= 0) & (episode.rewards <= 1))


def test_an_episode_that_runs_to_the_horizon_is_not_terminated(parts):
    episode = random_episode(parts, seed=0)
    assert not episode.terminated and episode.length == parts.task.horizon
    np.testing.assert_array_equal(episode.env_rewards, episode.rewards)  # cart-pole's own reward is the task's


class _StillPropagator:
    """A propagator whose predicted states stay at the start: `H+1 x D`."""

    def rollout(self, start, horizon):
        states = Gaussian(start.mean.expand(horizon + 1, -1), start.cov.expand(horizon + 1, -1, -1))
        return SimpleNamespace(states=states)


def end_lines(figure: Figure) -> list[tuple[float, str]]:
    """(x, label) of every vertical line on the figure's panels."""
    return [(float(line.get_xdata()[0]), line.get_label()) for ax in figure.axes for line in ax.lines
            if len(set(np.atleast_1d(line.get_xdata()))) == 1 and "at step" in line.get_label()]


def test_the_prediction_figure_marks_where_a_terminated_episode_ended(spinner):
    start = Gaussian(torch.zeros(3, dtype=torch.float64), 0.01 * torch.eye(3, dtype=torch.float64))
    states = np.zeros((5, 3))
    ended = Episode(states, np.zeros((4, 1)), np.zeros(4), np.zeros(4), terminated=True)
    figure = prediction_figure(_StillPropagator(), start, spinner.horizon, ended, "ended", spinner.state_names)
    assert end_lines(figure) == [(4.0, "terminated at step 4")] * 3  # one per state panel
    assert "terminated at step 4" in [t.get_text() for t in figure.axes[0].get_legend().get_texts()]
    full = Episode(np.zeros((spinner.horizon + 1, 3)), np.zeros((spinner.horizon, 1)), np.zeros(spinner.horizon),
                   np.zeros(spinner.horizon))
    assert end_lines(prediction_figure(_StillPropagator(), start, spinner.horizon, full, "full")) == []
