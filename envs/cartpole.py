"""Cart-pole swing-up (TASKS.md, "Cart-pole swing-up"): a uniform rod hinged on a driven cart."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, ClassVar

import gymnasium
import numpy as np
from gymnasium import spaces

from qtl.envs import _render
from qtl.envs._rk4 import n_substeps, rk4_step
from qtl.envs._validation import (
    action_vector,
    check_render_mode,
    finite_array,
    nonnegative,
    positive,
    positive_integer,
    require,
    state_option,
)
from qtl.envs.rewards import SaturatingReward

STATE_DIM = 4
ACTION_DIM = 1
# Index of θ in the state [x, ẋ, θ, θ̇]; the reward sees it through (sin θ, cos θ).
ANGLE_DIM = 2

DEFAULT_CART_MASS = 0.5  # M, kg
DEFAULT_POLE_MASS = 0.5  # m, kg (the source task; targets 0.8, 1.0, 1.5, 2.0)
DEFAULT_POLE_LENGTH = 0.6  # l, m (the paper's value)
DEFAULT_FRICTION = 0.1  # b, N s / m
DEFAULT_GRAVITY = 9.82  # g, m / s²
DEFAULT_MAX_FORCE = 10.0  # u_max, N
DEFAULT_DT = 0.1  # s, one decision (zero-order hold)
DEFAULT_INTEGRATOR_DT = 0.01  # s, RK4 sub-step
DEFAULT_HORIZON = 50  # decisions (5 s)
DEFAULT_START_STD = 0.1  # x_0 ~ N(0, 0.1² I)
DEFAULT_OBS_NOISE_STD = 0.0
DEFAULT_REWARD_WIDTH = 0.25  # σ_c, m
DEFAULT_TRACK_LIMIT = None  # m, half the track's length; None: an unbounded track that never ends an episode

# Rendering: a window on the origin that follows the cart only when the cart would leave it.
_RENDER_WIDTH_PX = 600
_RENDER_HALF_WIDTH = 2.4  # m of track either side of the view centre
_RENDER_CART_SIZE = (0.4, 0.2)  # m
_RENDER_POLE_WIDTH = 0.05  # m
_RENDER_MARGIN = 0.25  # m around the swept disc of the pole
_RENDER_END_HEIGHT = 0.15  # m above and below the track, the marks of a track_limit


class CartPoleSwingUpEnv(gymnasium.Env):
    r"""
    ## Description

    The cart-pole swing-up of PILCO (Deisenroth & Rasmussen, 2011) as used by the QTL paper: a
    uniform rod of length `l` and mass `m` hangs from a cart of mass `M` that a horizontal force
    `u` drives along a track with viscous friction `b`, unbounded unless `track_limit` is set.
    The pole starts hanging down and must be swung up and balanced with its tip above the track
    origin. The transfer tasks change `pole_mass` (source 0.5 kg; targets 0.8, 1.0, 1.5, 2.0 kg).

    With θ = 0 hanging down and θ = π upright, the tip is at (x + l sin θ, −l cos θ) and

        ẍ = (2 m l θ̇² sin θ + 3 m g sin θ cos θ + 4u − 4bẋ) / (4(M+m) − 3 m cos²θ)
        θ̈ = (−3 m l θ̇² sin θ cos θ − 6(M+m) g sin θ − 6(u − bẋ) cos θ) / (l (4(M+m) − 3 m cos²θ))

    integrated with RK4 at `integrator_dt` inside each control step of `dt` (zero-order hold).

    ## Action Space

    An `ndarray` with shape `(1,)` in [−1, 1], the force as a fraction of `max_force`; actions
    outside the box are clipped.

    | Num | Action                 | Min  | Max |
    |-----|------------------------|------|-----|
    | 0   | force u / `max_force`  | -1.0 | 1.0 |

    ## Observation Space

    An `ndarray` with shape `(4,)` (float64), the state plus optional Gaussian noise of std
    `obs_noise_std`. θ is not wrapped (the learner uses sin θ and cos θ), so every bound is
    infinite.

    | Num | Observation             | Min  | Max |
    |-----|-------------------------|------|-----|
    | 0   | cart position x (m)     | -Inf | Inf |
    | 1   | cart velocity ẋ (m/s)   | -Inf | Inf |
    | 2   | pole angle θ (rad)      | -Inf | Inf |
    | 3   | pole angular rate θ̇     | -Inf | Inf |

    ## Rewards

    The saturating reward of Eq. 13 with PILCO's cost width σ_c = `reward_width`:
    *r = exp(−d² / (2 σ_c²))*, d the distance of the pole tip to the target (0, l) above the
    track origin, *d² = x² + 2 x l sin θ + 2 l² + 2 l² cos θ*. It is 1 with the pole upright over
    the origin and about 1e−5 hanging down at rest. `step` scores the successor state (noise
    free). The same reward is available declaratively as `reward_spec`, a
    `SaturatingReward` over y = [x, ẋ, θ̇, sin θ, cos θ] with target y* = [0, 0, 0, 0, −1] and
    W = CᵀC, where C (y − y*) = tip − target.

    ## Starting State

    x_0 ~ N(0, diag(`start_std`²)), by default N(0, 0.1² I): the pole hanging down, the cart near
    the origin, nearly at rest. `reset(options={"state": s})` starts from the given state
    s = [x, ẋ, θ, θ̇] (4 finite numbers) instead.

    ## Episode Termination

    By default the episode never terminates (the swing-up on an unbounded track has no terminal
    states). With `track_limit` set, it terminates (`terminated=True`) at the first step whose
    successor state (noise free) has |x| > `track_limit`, the cart off the end of its track, as
    gymnasium's CartPole does at |x| > 2.4; that step's reward is still the reward of its state.
    The task's YAML declares the same bound as a constraint (`task.constraints`), which is what
    the learner reads: the env only enforces it.

    ## Episode Truncation

    The episode is truncated after `horizon` steps (default 50, i.e. 5 s).

    ## Arguments

    - `cart_mass`: M, the cart mass in kg (default 0.5).
    - `pole_mass`: m, the pole mass in kg; the transfer targets are 0.8, 1.0, 1.5 and 2.0
      (default 0.5).
    - `pole_length`: l, the pole length in m (default 0.6).
    - `friction`: b, the viscous cart friction in N s/m (default 0.1).
    - `gravity`: g in m/s² (default 9.82).
    - `max_force`: the force in N that the action 1.0 applies (default 10).
    - `dt`: the control period in s (default 0.1).
    - `integrator_dt`: the largest RK4 sub-step in s (default 0.01); `dt` is split into
      ceil(`dt` / `integrator_dt`) equal sub-steps.
    - `horizon`: steps until truncation (default 50).
    - `start_std`: std of the Gaussian start state around 0, a scalar or one per dimension
      (default 0.1).
    - `obs_noise_std`: std of the Gaussian observation noise; TASKS.md's optional value is 0.01
      (default 0).
    - `reward_width`: σ_c of the reward in m (default 0.25).
    - `track_limit`: half the track's length in m: the episode terminates once |x| exceeds it
      (default `None`, an unbounded track; `task=cartpole_track` sets 0.7).
    - `render_mode`: `None` or `"rgb_array"`.

    ```python
    >>> import gymnasium, envs
    >>> env = gymnasium.make("qtl/CartPoleSwingUp-v0", pole_mass=2.0)  # the 2 kg target
    ```
    """

    # The observation's dimensions, for axis labels and tables.
    state_names: ClassVar[tuple[str, ...]] = ("x (m)", "ẋ (m/s)", "θ (rad)", "θ̇ (rad/s)")
    metadata: ClassVar[dict[str, Any]] = {
        "render_modes": ["rgb_array"],
        "render_fps": round(1.0 / DEFAULT_DT),
    }

    def __init__(
        self,
        cart_mass: float = DEFAULT_CART_MASS,
        pole_mass: float = DEFAULT_POLE_MASS,
        pole_length: float = DEFAULT_POLE_LENGTH,
        friction: float = DEFAULT_FRICTION,
        gravity: float = DEFAULT_GRAVITY,
        max_force: float = DEFAULT_MAX_FORCE,
        dt: float = DEFAULT_DT,
        integrator_dt: float = DEFAULT_INTEGRATOR_DT,
        horizon: int = DEFAULT_HORIZON,
        start_std: float | tuple[float, ...] = DEFAULT_START_STD,
        obs_noise_std: float = DEFAULT_OBS_NOISE_STD,
        reward_width: float = DEFAULT_REWARD_WIDTH,
        track_limit: float | None = DEFAULT_TRACK_LIMIT,
        render_mode: str | None = None,
    ) -> None:
        # Checked in this order, so the first bad argument is the one reported.
        self.cart_mass = positive("cart_mass", cart_mass)
        self.pole_mass = positive("pole_mass", pole_mass)
        self.pole_length = positive("pole_length", pole_length)
        self.max_force = positive("max_force", max_force)
        self.dt = positive("dt", dt)
        positive("integrator_dt", integrator_dt)
        reward_width = positive("reward_width", reward_width)
        self.friction = nonnegative("friction", friction)
        self.gravity = nonnegative("gravity", gravity)
        self.obs_noise_std = nonnegative("obs_noise_std", obs_noise_std)
        self.track_limit = None if track_limit is None else positive("track_limit", track_limit)
        require(integrator_dt <= dt, "integrator_dt", integrator_dt, f"<= dt = {dt}")
        self.horizon = positive_integer("horizon", horizon)
        self.start_mean = np.zeros(STATE_DIM)
        self.start_std = finite_array(
            "start_std",
            start_std,
            STATE_DIM,
            f"a finite number >= 0 or {STATE_DIM} of them",
            minimum=0.0,
            scalar_ok=True,
        )
        self.render_mode = check_render_mode(render_mode, self.metadata["render_modes"])

        self.n_substeps = n_substeps(self.dt, integrator_dt)
        self.integrator_dt = self.dt / self.n_substeps
        self.metadata = {**self.metadata, "render_fps": max(1, round(1.0 / self.dt))}
        self.reward_spec = self._make_reward_spec(self.pole_length, reward_width)

        self.action_space = spaces.Box(-1.0, 1.0, shape=(ACTION_DIM,), dtype=np.float64)
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(STATE_DIM,), dtype=np.float64)

        self.state: np.ndarray | None = None
        self.last_force = 0.0
        self._steps = 0

    # ---- reward ------------------------------------------------------------------------------
    @staticmethod
    def _make_reward_spec(pole_length: float, width: float) -> SaturatingReward:
        """The tip-distance reward in the augmented coordinates y = [x, ẋ, θ̇, sin θ, cos θ].

        C maps y − y* (y* = [0, 0, 0, 0, −1]) to tip − target = (x + l sin θ, −l (cos θ + 1)),
        so (y − y*)ᵀ CᵀC (y − y*) = d² = x² + 2 x l sin θ + 2 l² + 2 l² cos θ.
        """
        ell = pole_length
        c = np.array([[1.0, 0.0, 0.0, ell, 0.0], [0.0, 0.0, 0.0, 0.0, -ell]])
        return SaturatingReward(
            state_dim=STATE_DIM,
            angle_dims=(ANGLE_DIM,),
            target=(0.0, 0.0, 0.0, 0.0, -1.0),
            weight=c.T @ c,
            width=width,
        )

    # ---- physics -----------------------------------------------------------------------------
    def _derivative(self, s: Sequence[float], force: float) -> tuple[float, float, float, float]:
        """d/dt [x, ẋ, θ, θ̇] of TASKS.md's uniform-rod equations (plain floats for speed)."""
        _, xd, th, thd = s
        big_m, m, ell, b, g = (
            self.cart_mass,
            self.pole_mass,
            self.pole_length,
            self.friction,
            self.gravity,
        )
        sin, cos = math.sin(th), math.cos(th)
        drive = force - b * xd
        denom = 4.0 * (big_m + m) - 3.0 * m * cos * cos
        xdd = (2.0 * m * ell * thd * thd * sin + 3.0 * m * g * sin * cos + 4.0 * drive) / denom
        thdd = (-3.0 * m * ell * thd * thd * sin * cos - 6.0 * (big_m + m) * g * sin - 6.0 * drive * cos) / (
            ell * denom
        )
        return (xd, xdd, thd, thdd)

    def _integrate(self, state: np.ndarray, force: float) -> np.ndarray:
        """RK4 over one control period `dt` with the force held constant."""
        s = [float(v) for v in state]
        for _ in range(self.n_substeps):
            s = rk4_step(self._derivative, s, self.integrator_dt, force)
        return np.array(s, dtype=float)

    def energy(self, state: np.ndarray | None = None) -> float:
        """Total mechanical energy (J) of `state` (default: the current state), zero at rest level.

        E = (M+m) ẋ²/2 + m l² θ̇²/6 + m l (ẋ θ̇ − g) cos θ / 2, the kinetic energy of cart and rod
        (rod inertia m l²/12 about its centre) plus the rod's potential energy −m g (l/2) cos θ.
        """
        s = self.state if state is None else np.asarray(state, dtype=float)
        if s is None:
            raise gymnasium.error.ResetNeeded("call reset() before energy() without a state")
        _, xd, th, thd = (float(v) for v in s)
        big_m, m, ell, g = self.cart_mass, self.pole_mass, self.pole_length, self.gravity
        return 0.5 * (big_m + m) * xd**2 + m * ell**2 * thd**2 / 6.0 + 0.5 * m * ell * (xd * thd - g) * math.cos(th)

    def tip_position(self, state: np.ndarray | None = None) -> np.ndarray:
        """World position (m) of the pole tip, (x + l sin θ, −l cos θ), the track at height 0."""
        s = self.state if state is None else np.asarray(state, dtype=float)
        if s is None:
            raise gymnasium.error.ResetNeeded("call reset() before tip_position() without a state")
        return np.array([s[0] + self.pole_length * np.sin(s[2]), -self.pole_length * np.cos(s[2])])

    # ---- gymnasium API -----------------------------------------------------------------------
    def _observe(self) -> np.ndarray:
        assert self.state is not None
        obs = self.state.copy()
        if self.obs_noise_std > 0:
            obs += self.obs_noise_std * self.np_random.standard_normal(STATE_DIM)
        return obs

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Draw x_0 ~ N(`start_mean`, diag(`start_std`²)), or use `options["state"]`."""
        super().reset(seed=seed)
        state = state_option(options, STATE_DIM)
        if state is None:
            state = self.start_mean + self.start_std * self.np_random.standard_normal(STATE_DIM)
        self.state = state
        self._steps = 0
        self.last_force = 0.0
        return self._observe(), {"state": self.state.copy()}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Apply the force for `dt`; the reward scores the (noise-free) successor state."""
        if self.state is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        a = action_vector(action, ACTION_DIM)
        force = self.max_force * float(np.clip(a[0], -1.0, 1.0))
        self.state = self._integrate(self.state, force)
        self.last_force = force
        self._steps += 1
        reward = float(self.reward_spec(self.state))
        terminated = self.track_limit is not None and abs(float(self.state[0])) > self.track_limit
        truncated = self._steps >= self.horizon
        return self._observe(), reward, terminated, truncated, {"state": self.state.copy()}

    def render(self) -> np.ndarray | None:
        """An `H x W x 3` `uint8` frame: track (its ends in red if limited), cart, pole, target tip and force arrow."""
        if self.render_mode is None:
            _render.warn_no_render_mode()
            return None
        state = self.start_mean if self.state is None else self.state
        x, _, th, _ = (float(v) for v in state)
        ell = self.pole_length
        reach = ell + _RENDER_MARGIN
        half_width = max(_RENDER_HALF_WIDTH, 2.0 * reach)
        # Keep the origin (and the target) in the middle; follow the cart only as far as needed.
        slack = half_width - reach
        center = min(max(0.0, x - slack), x + slack)
        canvas = _render.Canvas(
            _RENDER_WIDTH_PX,
            (center - half_width, center + half_width),
            (-reach, reach),
            background=_render.WHITE,
        )
        cart_w, cart_h = _RENDER_CART_SIZE
        # Track, with ticks every metre so motion of a re-centred view stays visible.
        canvas.line((center - half_width, 0.0), (center + half_width, 0.0), 0.02, _render.GREY)
        for tick in np.arange(np.ceil(center - half_width), center + half_width + 1e-9):
            canvas.line((tick, -0.03), (tick, 0.03), 0.015, _render.GREY)
        if self.track_limit is not None:  # the track's ends, where the episode terminates
            for end in (-self.track_limit, self.track_limit):
                canvas.line((end, -_RENDER_END_HEIGHT), (end, _RENDER_END_HEIGHT), 0.02, _render.RED)
        # Target tip position (0, l).
        arm = 0.06
        canvas.line((-arm, ell - arm), (arm, ell + arm), 0.02, _render.RED)
        canvas.line((-arm, ell + arm), (arm, ell - arm), 0.02, _render.RED)
        # Cart and force arrow.
        canvas.rectangle((x, 0.0), (cart_w, cart_h), _render.DARK_GREY)
        if self.last_force != 0.0:
            length = 0.5 * cart_w * self.last_force / self.max_force
            y_arrow = -0.5 * cart_h - 0.06
            canvas.arrow((x, y_arrow), (x + length, y_arrow), 0.025, _render.GREEN)
        # Pole, pivot and tip.
        tip = (x + ell * math.sin(th), -ell * math.cos(th))
        canvas.line((x, 0.0), tip, _RENDER_POLE_WIDTH, _render.ORANGE)
        canvas.circle((x, 0.0), 0.03, _render.BLACK)
        canvas.circle(tip, 0.035, _render.BLUE)
        return canvas.frame()

    def close(self) -> None:
        """Nothing to release (no window is ever opened)."""
