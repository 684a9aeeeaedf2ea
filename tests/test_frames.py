"""Episodes rendered: a frame per env step (held steps included), the task's wrappers, replays that touch no RNG."""

from __future__ import annotations

import dataclasses
import logging
import random
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from qtl.config.validate import checked_task
from qtl.env_wrappers import ActionRepeat, CenteredAction
from qtl.errors import UserError
from qtl.frames import FrameRecorder, episode_video, render_env, rendered_episode, replayed_clip
from qtl.task import Task
from tests.helpers import tiny_config
from tests.toy_envs import spinner_task

SEED = 11


def task_of(*overrides: str) -> Task:
    """The task of the tiny config with ``overrides`` (8 steps of the cart-pole by default)."""
    return checked_task(OmegaConf.to_container(tiny_config(*overrides).task, resolve=True))


@pytest.fixture(scope="module")
def held() -> Task:
    """The tiny cart-pole with each action held two env steps."""
    return task_of("task.action_repeat=2")


def swinging(task: Task):
    """An actor that pushes one way, then the other."""
    steps = iter(range(10**6))
    return lambda _obs: task.action_bound * (1.0 if next(steps) % 6 < 3 else -1.0)


def qtl_wrappers(env: gymnasium.Env) -> list[type]:
    """The qtl wrapper types around an env, outermost first (the frame recorder left out)."""
    found = []
    while isinstance(env, gymnasium.Wrapper):
        if isinstance(env, (ActionRepeat, CenteredAction)):
            found.append(type(env))
        env = env.env
    return found


def test_every_env_step_is_a_frame_the_held_ones_included(held):
    episode, clip = rendered_episode(held, swinging(held), SEED)
    assert episode.length == held.horizon == 8
    assert len(clip.frames) == held.action_repeat * episode.length + 1 == 17
    assert clip.fps == 10.0  # the cart-pole's dt is 0.1 s
    assert len({frame.tobytes() for frame in clip.frames}) > 1


@pytest.mark.parametrize("repeat", [1, 2])
def test_the_rendering_env_is_the_tasks_env_with_a_recorder_below_its_wrappers(repeat):
    task = task_of(f"task.action_repeat={repeat}")
    env, recorder = render_env(task)
    with task.make_env() as plain:
        assert qtl_wrappers(env) == qtl_wrappers(plain)
    assert isinstance(recorder, FrameRecorder) and env.unwrapped.render_mode == "rgb_array"
    assert len(recorder.frames) == 1  # the renderer was tried at once, before any episode
    env.close()


def test_a_replay_shows_the_same_episode_and_leaves_every_global_rng_where_it_was(held):
    rng = np.random.default_rng(0)
    episode, clip = rendered_episode(held, lambda _obs: rng.uniform(-held.action_bound, held.action_bound), SEED)
    random.seed(1), np.random.seed(1), torch.manual_seed(1)  # noqa: NPY002
    before = (random.getstate(), np.random.get_state()[1].copy(), torch.get_rng_state())  # noqa: NPY002
    replay = replayed_clip(held, episode, SEED)
    assert random.getstate() == before[0] and np.array_equal(np.random.get_state()[1], before[1])  # noqa: NPY002
    assert torch.equal(torch.get_rng_state(), before[2])
    assert np.array_equal(replay.frames, clip.frames) and replay.fps == clip.fps


def test_a_replay_that_does_not_retrace_the_episode_says_so(held, caplog):
    episode, _ = rendered_episode(held, swinging(held), SEED)
    moved = dataclasses.replace(episode, states=episode.states + 1.0)
    with caplog.at_level(logging.WARNING, logger="qtl.frames"):
        replayed_clip(held, moved, SEED)
    assert "did not retrace its states" in caplog.text


def test_an_env_that_draws_no_frames_is_one_line_and_a_run_goes_on_without_its_video(held, caplog):
    spinner = checked_task(spinner_task())
    with pytest.raises(UserError, match=r"draws no frames: its render modes are none, not 'rgb_array'") as caught:
        render_env(spinner)
    assert "\n" not in str(caught.value)
    episode, _ = rendered_episode(held, swinging(held), SEED)
    with caplog.at_level(logging.WARNING, logger="qtl.frames"):
        assert episode_video(spinner, episode, SEED) is None
    assert "no video of this episode (video=false turns them off)" in caplog.text


SHIPPED_TASKS = sorted(p.stem for p in (Path(__file__).resolve().parents[1] / "configs" / "task").glob("*.yaml"))


@pytest.mark.parametrize("name", SHIPPED_TASKS)
def test_every_shipped_task_renders_a_frame_per_env_step(name):
    """qtl-play and the TensorBoard videos draw every task qtl ships: its own envs, gymnasium's, MuJoCo's."""
    if name == "inverted_pendulum":
        pytest.importorskip("mujoco", reason="the mujoco extra (bash scripts/setup.sh --mujoco) draws this task")
    task = task_of(f"task={name}", "task.horizon=3", "task.success.last_steps=1")
    episode, clip = rendered_episode(task, lambda _obs: np.zeros(task.action_dim), SEED)  # too gentle to end it
    steps = len(episode.actions) * task.action_repeat
    assert len(clip.frames) == steps + 1  # the start's frame, then one per env step
    assert clip.frames.shape[1] >= 64 and clip.frames.shape[2] >= 64 and clip.fps > 0
    assert np.ptp(clip.frames[0]) > 0  # a picture, not a blank
