"""Continuous mountain car (TASKS.md, "Mountain car"): Sutton & Barto's map with engine power P."""

from __future__ import annotations

import math
from typing import Any, ClassVar

import gymnasium
import numpy as np
from gymnasium import spaces

from qtl.envs import _render
from qtl.envs._validation import (
    action_vector,
    check_render_mode,
    finite_array,
    nonnegative,
    nonzero,
    positive,
    positive_integer,
    require,
    state_option,
)
from qtl.envs.rewards import SaturatingReward

STATE_DIM = 2
ACTION_DIM = 1

BASE_POWER = 0.001  # P at power factor 1.0 (not gymnasium's 0.0015: see TASKS.md)
GRAVITY_TERM = 0.0025  # the −0.0025 cos 3x slope term of the map
HILL_FREQUENCY = 3.0  # the track's height is sin(3x)
MAX_SPEED = 0.07
MIN_POSITION = -1.2  # the left wall
MAX_POSITION = 0.6
GOAL_POSITION = 0.5  # target (0.5, 0): reach the goal and stop there

DEFAULT_POWER = 1.0  # engine power factor (source 1.0; targets 0.5, 1.5, 3.0)
DEFAULT_ACTION_REPEAT = 5  # map steps per decision
DEFAULT_HORIZON = 80  # decisions
DEFAULT_START_MEAN = (-0.5, 0.0)
DEFAULT_START_STD = (0.05, 1e-4)  # diag(0.05², tiny): the velocity std keeps Σ_0 positive
DEFAULT_VELOCITY_WEIGHT = 0.0
DEFAULT_REWARD_WIDTH = 0.25  # σ_c, the same cost width as every task of TASKS.md
DEFAULT_OBS_NOISE_STD = 0.0

# Rendering
_RENDER_WIDTH_PX = 600
_RENDER_HEIGHT_SCALE = 0.45  # the track is drawn as 0.45 sin(3x), as in the classic picture
_RENDER_Y_RANGE = (-0.52, 0.66)
_RENDER_CURVE_POINTS = 200
_RENDER_CAR_SIZE = (0.16, 0.07)
_RENDER_WHEEL_RADIUS = 0.025
_RENDER_FLAG_HEIGHT = 0.15


def track_height(position: np.ndarray | float) -> np.ndarray | float:
    """Height sin(3x) of the track at `position` (the map's potential, up to scale)."""
    return np.sin(HILL_FREQUENCY * np.asarray(position, dtype=float))


def map_step(position: float, velocity: float, action: float, power: float) -> tuple[float, float]:
    """One step of the mountain-car map with action `action` ∈ [−1, 1] and power factor `power`.

    v ← clip(v + P a − 0.0025 cos 3x, ±0.07); x ← clip(x + v, [−1.2, 0.6]); hitting the left wall
    sets v = 0. P = 0.001 × `power`. The right end only clips the position (TASKS.md).
    """
    velocity += BASE_POWER * power * action - GRAVITY_TERM * math.cos(HILL_FREQUENCY * position)
    velocity = min(max(velocity, -MAX_SPEED), MAX_SPEED)
    position = min(max(position + velocity, MIN_POSITION), MAX_POSITION)
    if position <= MIN_POSITION and velocity < 0:
        velocity = 0.0
    return position, velocity


class MountainCarEnv(gymnasium.Env):
    r"""
    ## Description

    Sutton & Barto's mountain car with a continuous throttle, as used by the QTL paper: an
    under-powered car in the valley between two hills (track height sin 3x) must rock back and
    forth to climb the right hill, reach x = 0.5 and stop there. The transfer tasks change the
    engine power factor `power` (source 1.0; targets 0.5, 1.5, 3.0). With the engine force
    P = 0.001 × `power` (not gymnasium's 0.0015), full throttle from the valley cannot climb the
    right hill directly at 0.5, 1.0 and 1.5, and can at 3.0 (the threshold is ≈ 1.8).

    One decision applies the action for `action_repeat` steps of the map

        v ← clip(v + P a − 0.0025 cos 3x, ±0.07);  x ← clip(x + v, [−1.2, 0.6]);

    hitting the left wall (x = −1.2) sets v = 0; the right end (x = 0.6) only clips x.

    ## Action Space

    An `ndarray` with shape `(1,)` in [−1, 1], the throttle; actions outside are clipped.

    | Num | Action   | Min  | Max |
    |-----|----------|------|-----|
    | 0   | throttle | -1.0 | 1.0 |

    ## Observation Space

    An `ndarray` with shape `(2,)` (float64), the state plus optional Gaussian noise of std
    `obs_noise_std`. The bounds are the track and speed limits (infinite when there is
    observation noise, which is unbounded).

    | Num | Observation | Min   | Max  |
    |-----|-------------|-------|------|
    | 0   | position x  | -1.2  | 0.6  |
    | 1   | velocity v  | -0.07 | 0.07 |

    ## Rewards

    The saturating reward of Eq. 13, *r = exp(−d² / (2 σ_c²))* with
    *d² = (x − 0.5)² + `velocity_weight` v²* and σ_c = `reward_width`, scoring the successor
    state of each decision. Default σ_c = 0.25, the width TASKS.md fixes for all tasks (reward
    "close to zero" beyond about 0.6 from the target): r = 1 at the goal, r ≈ 0.61 at x = 0.25,
    r ≈ 0.06 at x = −0.1, and r ≈ 3e−4 in the valley (x ≈ −0.5, d ≈ 1), so the car must leave the
    valley to be rewarded at all. The same reward is available declaratively as `reward_spec`,
    a `SaturatingReward` with target (0.5, 0) and W = diag(1, `velocity_weight`).

    ## Starting State

    x_0 ~ N(`start_mean`, diag(`start_std`²)), by default N((−0.5, 0), diag(0.05², 1e−4²)): near
    the valley floor (x = −π/6), at rest; the state is clipped to the track and speed limits.
    `reset(options={"state": s})` starts from the given state s = (x, v) (2 finite numbers)
    instead, clipped likewise.

    ## Episode Truncation

    The episode never terminates (reaching the goal is not terminal: the car must stay there); it
    is truncated after `horizon` decisions (default 80, i.e. 400 map steps).

    ## Arguments

    - `power`: the engine power factor, P = 0.001 × `power`; the transfer targets are 0.5, 1.5
      and 3.0 (default 1.0). A negative factor reverses the engine (a mirrored actuator: throttle
      +1 pushes left), a far target for transfer.
    - `action_repeat`: map steps per decision (default 5).
    - `horizon`: decisions until truncation (default 80).
    - `start_mean`: mean (x, v) of the start state (default (−0.5, 0)).
    - `start_std`: per-dimension std of the start state (default (0.05, 1e−4)).
    - `velocity_weight`: weight of v² in d² (default 0).
    - `reward_width`: σ_c of the reward (default 0.25).
    - `obs_noise_std`: std of the Gaussian observation noise (default 0).
    - `render_mode`: `None` or `"rgb_array"`.

    ```python
    >>> import gymnasium, envs
    >>> env = gymnasium.make("qtl/MountainCar-v0", power=3.0)  # the 300 % target
    ```
    """

    # The observation's dimensions, for axis labels and tables.
    state_names: ClassVar[tuple[str, ...]] = ("x", "v")
    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        power: float = DEFAULT_POWER,
        action_repeat: int = DEFAULT_ACTION_REPEAT,
        horizon: int = DEFAULT_HORIZON,
        start_mean: tuple[float, float] = DEFAULT_START_MEAN,
        start_std: tuple[float, float] = DEFAULT_START_STD,
        velocity_weight: float = DEFAULT_VELOCITY_WEIGHT,
        reward_width: float = DEFAULT_REWARD_WIDTH,
        obs_noise_std: float = DEFAULT_OBS_NOISE_STD,
        render_mode: str | None = None,
    ) -> None:
        self.power = nonzero("power", power)
        reward_width = positive("reward_width", reward_width)
        self.velocity_weight = nonnegative("velocity_weight", velocity_weight)
        self.obs_noise_std = nonnegative("obs_noise_std", obs_noise_std)
        self.action_repeat = positive_integer("action_repeat", action_repeat)
        self.horizon = positive_integer("horizon", horizon)
        mean = finite_array("start_mean", start_mean, STATE_DIM, "two finite numbers (x, v)")
        require(
            MIN_POSITION <= mean[0] <= MAX_POSITION and abs(mean[1]) <= MAX_SPEED,
            "start_mean",
            start_mean,
            f"on the track [{MIN_POSITION}, {MAX_POSITION}] with |v| <= {MAX_SPEED}",
        )
        self.start_mean = mean
        self.start_std = finite_array("start_std", start_std, STATE_DIM, "two finite numbers >= 0", minimum=0.0)
        self.render_mode = check_render_mode(render_mode, self.metadata["render_modes"])
        self.reward_spec = SaturatingReward(
            state_dim=STATE_DIM,
            angle_dims=(),
            target=(GOAL_POSITION, 0.0),
            weight=np.diag([1.0, self.velocity_weight]),
            width=reward_width,
        )

        self.action_space = spaces.Box(-1.0, 1.0, shape=(ACTION_DIM,), dtype=np.float64)
        if self.obs_noise_std > 0:
            low = np.full(STATE_DIM, -np.inf)
            high = np.full(STATE_DIM, np.inf)
        else:
            low = np.array([MIN_POSITION, -MAX_SPEED])
            high = np.array([MAX_POSITION, MAX_SPEED])
        self.observation_space = spaces.Box(low, high, dtype=np.float64)

        self.state: np.ndarray | None = None
        self.last_action = 0.0
        self._steps = 0
        self._render_background: _render.Canvas | None = None

    # ---- gymnasium API -----------------------------------------------------------------------
    def _observe(self) -> np.ndarray:
        assert self.state is not None
        obs = self.state.copy()
        if self.obs_noise_std > 0:
            obs += self.obs_noise_std * self.np_random.standard_normal(STATE_DIM)
        return obs

    @staticmethod
    def _clip_state(state: np.ndarray) -> np.ndarray:
        return np.array(
            [
                np.clip(state[0], MIN_POSITION, MAX_POSITION),
                np.clip(state[1], -MAX_SPEED, MAX_SPEED),
            ]
        )

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Draw x_0 ~ N(`start_mean`, diag(`start_std`²)) (clipped), or use `options["state"]`."""
        super().reset(seed=seed)
        state = state_option(options, STATE_DIM)
        if state is None:
            state = self.start_mean + self.start_std * self.np_random.standard_normal(STATE_DIM)
        self.state = self._clip_state(state)
        self._steps = 0
        self.last_action = 0.0
        return self._observe(), {"state": self.state.copy()}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Hold the throttle for `action_repeat` map steps; the reward scores the successor."""
        if self.state is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        a = action_vector(action, ACTION_DIM)
        throttle = float(np.clip(a[0], -1.0, 1.0))
        position, velocity = float(self.state[0]), float(self.state[1])
        for _ in range(self.action_repeat):
            position, velocity = map_step(position, velocity, throttle, self.power)
        self.state = np.array([position, velocity])
        self.last_action = throttle
        self._steps += 1
        reward = float(self.reward_spec(self.state))
        truncated = self._steps >= self.horizon
        return self._observe(), reward, False, truncated, {"state": self.state.copy()}

    def render(self) -> np.ndarray | None:
        """An `H x W x 3` `uint8` frame: hills, goal flag, the car tilted along the slope."""
        if self.render_mode is None:
            _render.warn_no_render_mode()
            return None
        state = self.start_mean if self.state is None else self.state
        x = float(state[0])
        if self._render_background is None:
            self._render_background = self._draw_background()
        canvas = self._render_background.copy()
        # Car: a body on two wheels, tilted to the local slope of the drawn track.
        slope = math.atan(_RENDER_HEIGHT_SCALE * HILL_FREQUENCY * math.cos(HILL_FREQUENCY * x))
        tangent = np.array([math.cos(slope), math.sin(slope)])
        normal = np.array([-tangent[1], tangent[0]])
        ground = np.array([x, _RENDER_HEIGHT_SCALE * float(track_height(x))])
        car_w, car_h = _RENDER_CAR_SIZE
        r = _RENDER_WHEEL_RADIUS
        body = ground + normal * (r + 0.5 * car_h)
        canvas.rectangle(body, _RENDER_CAR_SIZE, _render.BLUE, angle=slope)
        for side in (-1.0, 1.0):
            canvas.circle(ground + normal * r + side * 0.3 * car_w * tangent, r, _render.BLACK)
        # Throttle arrow above the car.
        if self.last_action != 0.0:
            base = body + normal * (0.5 * car_h + 0.06)
            canvas.arrow(base, base + 0.15 * self.last_action * tangent, 0.02, _render.GREEN)
        return canvas.frame()

    @staticmethod
    def _draw_background() -> _render.Canvas:
        """The static part of the picture: sky, hills and the goal flag."""
        canvas = _render.Canvas(_RENDER_WIDTH_PX, (MIN_POSITION, MAX_POSITION), _RENDER_Y_RANGE, background=_render.SKY)
        xs = np.linspace(MIN_POSITION, MAX_POSITION, _RENDER_CURVE_POINTS)
        ys = _RENDER_HEIGHT_SCALE * track_height(xs)
        canvas.fill_below(xs, ys, _render.BROWN)
        canvas.polyline(np.stack([xs, ys], axis=-1), 0.012, _render.DARK_GREY)
        goal_y = _RENDER_HEIGHT_SCALE * float(track_height(GOAL_POSITION))
        pole_top = (GOAL_POSITION, goal_y + _RENDER_FLAG_HEIGHT)
        canvas.line((GOAL_POSITION, goal_y), pole_top, 0.012, _render.BLACK)
        flag = np.array(
            [
                pole_top,
                (GOAL_POSITION + 0.08, pole_top[1] - 0.03),
                (GOAL_POSITION, pole_top[1] - 0.06),
            ]
        )
        canvas.polygon(flag, _render.RED)
        return canvas

    def close(self) -> None:
        """Nothing to release (no window is ever opened)."""
