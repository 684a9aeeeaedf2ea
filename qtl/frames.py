"""An episode on a task's env, rendered: a frame after the reset and after every env step, held steps included.

The env is the task's own (:meth:`qtl.task.Task.make_env`: the same kwargs and wrappers) made with
``render_mode="rgb_array"``, and a :class:`FrameRecorder` just above the env's own wrappers, below
:class:`~qtl.env_wrappers.ActionRepeat`: an action held ``action_repeat`` env steps gives that many frames. A clip of
T learner steps, each ``action_repeat`` env steps long, has ``T × action_repeat + 1`` frames at the env's rate.

Headless rendering (Linux without a display): an unset ``MUJOCO_GL`` is set to ``egl`` (MuJoCo's off-screen
OpenGL; ``osmesa`` is the software fallback), an unset ``SDL_VIDEODRIVER`` to ``dummy`` (pygame, which gymnasium's
classic-control envs draw with, draws off-screen anyway and would complain about the missing display).
"""

from __future__ import annotations

import logging
import os
import sys
from typing import Any, SupportsFloat

import gymnasium
import numpy as np
from gymnasium.envs.registration import load_env_creator

from qtl.checkpoint import rng_state, set_rng_state
from qtl.episodes import Actor, Episode, run_episode
from qtl.errors import UserError
from qtl.task import Task, env_spec
from qtl.video import Clip

log = logging.getLogger(__name__)

RGB_ARRAY = "rgb_array"
DEFAULT_FPS = 10.0  # an env that states neither its dt nor metadata["render_fps"]
HEADLESS_GL = "egl"  # MUJOCO_GL where none is set and there is no display (Linux)


class FrameRecorder(gymnasium.Wrapper):
    """Keeps ``env.render()`` after each reset (``frames`` starts over) and after each step."""

    def __init__(self, env: gymnasium.Env) -> None:
        """Record the frames of ``env``, made with ``render_mode="rgb_array"``."""
        super().__init__(env)
        self.frames: list[np.ndarray] = []

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Any, dict]:
        """The env's reset; its frame the first of a new list."""
        obs, info = self.env.reset(seed=seed, options=options)
        self.frames = [self._frame()]
        return obs, info

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        """The env's step; its frame appended."""
        out = self.env.step(action)
        self.frames.append(self._frame())
        return out

    def _frame(self) -> np.ndarray:
        frame = self.env.render()
        if not isinstance(frame, np.ndarray) or frame.ndim != 3 or frame.shape[-1] not in (3, 4):
            raise UserError(f"{self.env.spec.id if self.env.spec else self.env}: render() gave no `H x W x 3` image "
                            f"(got {type(frame).__name__})")
        return frame


def headless_defaults() -> None:
    """On Linux without a display: ``MUJOCO_GL=egl`` and ``SDL_VIDEODRIVER=dummy`` where unset (off-screen frames)."""
    display = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    if sys.platform.startswith("linux") and not display:
        os.environ.setdefault("MUJOCO_GL", HEADLESS_GL)
        os.environ.setdefault("SDL_VIDEODRIVER", "dummy")


def render_env(task: Task) -> tuple[gymnasium.Env, FrameRecorder]:
    """The task's env (:meth:`Task.make_env`'s wrappers) rendering ``rgb_array`` frames, and its frame recorder.

    Checked before any work: an env without an ``rgb_array`` renderer, or one whose renderer cannot start (a missing
    package, no OpenGL), is a one-line :class:`~qtl.errors.UserError`.
    """
    headless_defaults()
    declared = declared_render_modes(task.env_id)
    if declared is not None and RGB_ARRAY not in declared:
        raise UserError(f"task.env.id={task.env_id!r} draws no frames: its render modes are {declared or 'none'}, "
                        f"not {RGB_ARRAY!r}")
    recorders: list[FrameRecorder] = []

    def recording(env: gymnasium.Env) -> FrameRecorder:
        recorders.append(FrameRecorder(env))
        return recorders[-1]

    try:
        env = task.make_env(render_mode=RGB_ARRAY, inner=recording)
    except Exception as err:  # e.g. a factory whose env takes no render_mode
        raise UserError(f"cannot make task.env.id={task.env_id!r} with render_mode={RGB_ARRAY!r}: "
                        f"{type(err).__name__}: {_first_line(err)}") from err
    if getattr(env.unwrapped, "render_mode", None) != RGB_ARRAY:
        env.close()
        raise UserError(f"task.env.id={task.env_id!r} draws no frames: it was made with render_mode={RGB_ARRAY!r} "
                        f"and has render_mode={getattr(env.unwrapped, 'render_mode', None)!r}")
    recorder = recorders[0]
    try:
        recorder.reset(seed=0, options=task.reset_options)  # the renderer starts here (OpenGL, pygame)
    except UserError:
        env.close()
        raise
    except Exception as err:  # a renderer fails in its own ways: a missing package, no OpenGL context, ...
        env.close()
        first = _first_line(err)
        gl = (f" (MuJoCo draws with OpenGL, MUJOCO_GL={os.environ.get('MUJOCO_GL')}: try egl, osmesa or glfw)"
              if "mujoco" in type(err).__module__.lower() or "OpenGL" in first else "")
        raise UserError(f"cannot render task.env.id={task.env_id!r}: {type(err).__name__}: {first}{gl}") from err
    return env, recorder


def declared_render_modes(env_id: str) -> list[str] | None:
    """The render modes ``env_id``'s env class declares (``metadata["render_modes"]``); None for a factory function."""
    creator = env_spec(env_id).entry_point
    if isinstance(creator, str):
        creator = load_env_creator(creator)
    metadata = getattr(creator, "metadata", None)
    return list(metadata.get("render_modes") or []) if isinstance(metadata, dict) else None


def _first_line(err: BaseException) -> str:
    """The first non-blank line of an error's message (its type's name if none)."""
    return next((line.strip() for line in str(err).splitlines() if line.strip()), type(err).__name__)


def frame_rate(env: gymnasium.Env) -> float:
    """Frames per second of one frame per env step: 1/dt of the env if it says, else its ``render_fps``."""
    dt = getattr(env.unwrapped, "dt", None)
    if isinstance(dt, (int, float)) and dt > 0:
        return 1.0 / float(dt)
    fps = env.unwrapped.metadata.get("render_fps")
    return float(fps) if fps else DEFAULT_FPS


def rendered_episode(task: Task, act: Actor, seed: int) -> tuple[Episode, Clip]:
    """``act`` for one episode on the task's env reset with ``seed`` (:func:`qtl.episodes.run_episode`), rendered."""
    env, recorder = render_env(task)
    try:
        episode = run_episode(env, task, act, seed)
        return episode, Clip.of(recorder.frames, frame_rate(env))
    finally:
        env.close()


def replayed_clip(task: Task, real: Episode, seed: int) -> Clip:
    """The frames of an episode already run, by replaying its actions from the same seeded reset on a rendering env.

    The learner's env renders nothing (and rendering it would change nothing it computes): the replay is a second,
    separate env, as cheap as the env's steps and frames. The global RNG streams (Python, numpy, torch) are restored
    afterwards, so a run with videos draws exactly what one without draws. A replay that does not retrace the
    episode's states (an env whose steps depend on more than its seed and the actions) is logged, and kept.
    """
    actions = iter(real.actions)
    saved = rng_state()
    try:
        replay, clip = rendered_episode(task, lambda _obs: next(actions), seed)
    finally:
        set_rng_state(saved)
    if replay.states.shape != real.states.shape or not np.allclose(replay.states, real.states, rtol=0, atol=1e-9):
        log.warning("the video of this episode replays its actions on a fresh env and did not retrace its states: "
                    "the env depends on more than its seed and the actions")
    return clip


def episode_video(task: Task, real: Episode, seed: int) -> Clip | None:
    """:func:`replayed_clip` of an episode for TensorBoard; None, with a warning, where the env cannot be rendered."""
    try:
        return replayed_clip(task, real, seed)
    except UserError as err:
        log.warning("no video of this episode (video=false turns them off): %s", err)
        return None
