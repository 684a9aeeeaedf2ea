"""Quadcopter (source) and helicopter (target) take-off-and-hover tasks (TASKS.md, Section 5.3).

Two rigid-body models of our own behind one interface: the same 12-D observation, the same 4-D
action (collective and attitude set-points, each vehicle closing its own inner attitude loop),
the same task (take off from the ground, fly to (−1, −1, 1.5) and hold it), but different
thrust laws, drag, actuator lags, yaw coupling, lateral bias, inertia and ground-effect height.

Conventions shared by both vehicles:

- world frame z up, the ground the plane z = 0; body frame x forward, y left, z up;
- ZYX Euler angles (roll φ, pitch θ, yaw ψ): R = R_z(ψ) R_y(θ) R_x(φ) maps body to world, so
  a positive pitch tilts the thrust towards +x and a positive roll towards −y;
- the position (x, y, z) is that of the vehicle's reference point, the bottom of its landing
  gear below the centre of mass: it rests on the ground at z = 0.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
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
    finite_tuple,
    nonnegative,
    positive,
    positive_integer,
    require,
    state_option,
)
from qtl.envs.rewards import SaturatingReward

__all__ = [
    "AircraftEnv",
    "Autopilot",
    "HelicopterEnv",
    "QuadcopterEnv",
    "ground_effect_factor",
]

OBS_DIM = 12
ACTION_DIM = 4
N_ACTUATORS = 4
POSITION_DIMS = (0, 1, 2)
GRAVITY = 9.81  # m/s²

# Action scaling (both vehicles): roll / pitch set-points ±0.35 rad, yaw set-point ±π/2.
MAX_TILT_SETPOINT = 0.35  # rad
MAX_YAW_SETPOINT = 0.5 * math.pi  # rad

# Cheeseman–Bennett ground effect: T_IGE / T_OGE = 1 / (1 − (R / (4 z_r))²), with the rotor
# height z_r clipped below at R/2 and the factor clipped above at 1.5.
GROUND_EFFECT_MIN_HEIGHT_RATIO = 0.5  # z_r >= R / 2
GROUND_EFFECT_MAX_FACTOR = 1.5

# The task (TASKS.md): start at rest on the ground at the origin, fly to the target.
DEFAULT_TARGET = (-1.0, -1.0, 1.5)  # m
DEFAULT_DT = 0.1  # s, one decision (zero-order hold)
DEFAULT_INTEGRATOR_DT = 0.005  # s, RK4 sub-step
DEFAULT_HORIZON = 200  # decisions (20 s)
DEFAULT_START_XY_STD = 0.1  # m
DEFAULT_START_YAW_STD = 0.1  # rad
DEFAULT_OBS_NOISE_STD = 0.0
DEFAULT_REWARD_WIDTH = 0.25  # σ_c, m (TASKS.md, "Reward (all tasks)")

# ---- quadcopter defaults (AscTec Hummingbird-like X-frame) ----------------------------------
QUAD_MASS = 0.5  # kg
QUAD_INERTIA = (3.65e-3, 3.68e-3, 7.03e-3)  # kg m², principal axes
QUAD_ARM_LENGTH = 0.17  # m, centre to each motor
QUAD_THRUST_COEFFICIENT = 5.57e-6  # k_f, N s² (thrust = k_f ω²)
QUAD_TORQUE_COEFFICIENT = 1.36e-7  # k_m, N m s² (drag torque = k_m ω²)
QUAD_MOTOR_TIME_CONSTANT = 0.02  # s, first-order lag of each rotor speed
QUAD_MAX_ROTOR_SPEED = 800.0  # rad/s (3.6 N per rotor, 2.9× the weight in all)
QUAD_MAX_THRUST = 2.0 * QUAD_MASS * GRAVITY  # N at collective +1 (hover at 0)
QUAD_DRAG_COEFFICIENT = (0.05, 0.05, 0.1)  # N s²/m², quadratic drag along body x, y, z
QUAD_ROTOR_RADIUS = 0.1  # m
QUAD_ROTOR_HEIGHT = 0.06  # m, rotor plane above the landing gear
QUAD_ATTITUDE_KP = (225.0, 225.0, 25.0)  # rad/s² per rad (roll, pitch, yaw)
QUAD_ATTITUDE_KD = (21.0, 21.0, 7.0)  # rad/s² per rad/s
QUAD_RENDER_SCALE = 2.0  # drawn twice its size: 0.5 m across is small in a 4 m view
QUAD_AUTOPILOT_GAINS = {"kp_xy": 1.2, "kd_xy": 1.8, "kp_z": 2.0, "kd_z": 2.2}

# ---- helicopter defaults (XCell Tempest-like near-hover model, Abbeel et al. 2006) ----------
HELI_MASS = 5.0  # kg
HELI_INERTIA = (0.18, 0.34, 0.28)  # kg m²
HELI_MAX_THRUST = 2.0 * HELI_MASS * GRAVITY  # N at collective +1 (hover at 0)
HELI_VELOCITY_DAMPING = (0.18, 0.43, 0.49)  # 1/s, linear damping of body velocities u, v, w
HELI_RATE_DAMPING = (12.8, 10.1, 8.2)  # 1/s, damping of body rates p, q, r
HELI_ROTOR_TIME_CONSTANT = 0.08  # s, rotor / flapping lag of all four channels
HELI_CYCLIC_MOMENT = (11.5, 21.8)  # N m per unit lateral / longitudinal cyclic
HELI_TAIL_MOMENT = 11.2  # N m of yaw per unit pedal (tail-rotor thrust × tail arm)
HELI_TAIL_ARM = 0.8  # m, tail rotor behind the main shaft
HELI_MAIN_ROTOR_TORQUE_RATIO = 0.05  # m, main-rotor reaction torque per newton of thrust
HELI_ROTOR_RADIUS = 0.69  # m
HELI_ROTOR_HEIGHT = 0.35  # m, rotor hub above the skids
HELI_ATTITUDE_KP = (1.0, 1.0, 2.0)  # unit cyclic / pedal per rad (roll, pitch, yaw)
HELI_ATTITUDE_KD = (0.05, 0.05, 0.1)  # unit cyclic / pedal per rad/s
HELI_AUTOPILOT_GAINS = {"kp_xy": 0.8, "kd_xy": 1.4, "kp_z": 1.5, "kd_z": 1.8}

# Autopilot limits (both vehicles).
AUTOPILOT_MAX_HORIZONTAL_ACCEL = GRAVITY * math.tan(MAX_TILT_SETPOINT)  # m/s²
AUTOPILOT_MAX_CLIMB_ACCEL = 0.5 * GRAVITY  # m/s², up or down
AUTOPILOT_MIN_TILT_COSINE = 0.5  # bounds the 1 / (cos φ cos θ) thrust compensation

# Rendering: a top view (x–y) and a side view (x–z) side by side, vehicles drawn to scale.
_RENDER_VIEW_WIDTH_PX = 360
_RENDER_XY_RANGE = (-2.5, 1.5)  # m, both horizontal axes
_RENDER_Z_RANGE = (-0.4, 3.6)  # m, as tall as the top view
_RENDER_GAP_PX = 6
_RENDER_LINE = 0.035  # m
_RENDER_TARGET_ARM = 0.12  # m
_RENDER_GRID_STEP = 1.0  # m
_RENDER_CIRCLE_POINTS = 24


def _clip(value: float, limit: float) -> float:
    return -limit if value < -limit else (limit if value > limit else value)


def ground_effect_factor(rotor_height: float | np.ndarray, rotor_radius: float) -> float | np.ndarray:
    """Cheeseman–Bennett thrust ratio in / out of ground effect, 1 / (1 − (R / (4 z_r))²).

    `rotor_height` z_r (m, any shape) is the rotor plane's height above the ground, clipped below
    at R / 2 (where the formula gives 4/3); the factor is clipped above at 1.5. It is about 1.004
    at z_r = 4 R and tends to 1 higher up.
    """
    if not rotor_radius > 0:
        raise ValueError(f"rotor_radius must be > 0, got {rotor_radius!r}")
    z_r = np.maximum(np.asarray(rotor_height, dtype=float), GROUND_EFFECT_MIN_HEIGHT_RATIO * rotor_radius)
    factor = np.minimum(1.0 / (1.0 - (rotor_radius / (4.0 * z_r)) ** 2), GROUND_EFFECT_MAX_FACTOR)
    return float(factor) if factor.ndim == 0 else factor


class AircraftEnv(gymnasium.Env, ABC):
    """Shared interface and rigid-body core of :class:`QuadcopterEnv` and :class:`HelicopterEnv`.

    A vehicle subclass supplies its body-frame force and torque and the derivative of its four
    hidden actuator states (`_wrench`), its actuator state at rest and in hover, its trim roll
    and its drawing; both share the linear collective law T = (1 + c) / 2 · `max_thrust`
    (`collective_for_thrust`). The base class integrates

        ṗ = v,  v̇ = R F_b / m − g e_z,  η̇ = E(η) ω,  J ω̇ = τ_b − ω × J ω

    (p world position, v world velocity, η = (φ, θ, ψ), ω body rates, J diagonal) with RK4, and
    handles ground contact: a sub-step that would end below z = 0 ends at rest on the ground
    instead (z = 0, no velocity, level, x, y and ψ held), so a vehicle whose thrust cannot lift it
    neither sinks, slides nor tilts, and a landing is perfectly inelastic. It also owns the task:
    start distribution, reward, truncation, observation noise and rendering.
    """

    # The observation's dimensions, for axis labels and tables.
    state_names: ClassVar[tuple[str, ...]] = (
        "x (m)", "y (m)", "z (m)", "φ (rad)", "θ (rad)", "ψ (rad)",
        "ẋ (m/s)", "ẏ (m/s)", "ż (m/s)", "φ̇ (rad/s)", "θ̇ (rad/s)", "ψ̇ (rad/s)",
    )
    metadata: ClassVar[dict[str, Any]] = {
        "render_modes": ["rgb_array"],
        "render_fps": round(1.0 / DEFAULT_DT),
    }

    # Per-vehicle defaults of :class:`Autopilot`.
    AUTOPILOT_GAINS: ClassVar[dict[str, float]] = {}
    # Drawing scale of the vehicle in `render` (a small vehicle is drawn enlarged).
    RENDER_SCALE: ClassVar[float] = 1.0

    def __init__(
        self,
        *,
        mass: float,
        inertia: Sequence[float],
        rotor_radius: float,
        rotor_height: float,
        max_thrust: float,
        ground_effect: bool,
        dt: float,
        integrator_dt: float,
        horizon: int,
        obs_noise_std: float,
        reward_width: float,
        start_xy_std: float,
        start_yaw_std: float,
        target: Sequence[float],
        render_mode: str | None,
    ) -> None:
        self.mass = positive("mass", mass)
        self.inertia = finite_tuple("inertia", inertia, 3, positive=True)
        self.rotor_radius = positive("rotor_radius", rotor_radius)
        self.rotor_height = nonnegative("rotor_height", rotor_height)
        self.max_thrust = positive("max_thrust", max_thrust)
        require(isinstance(ground_effect, bool), "ground_effect", ground_effect, "True or False")
        self.ground_effect = ground_effect
        self.dt = positive("dt", dt)
        integrator_dt = positive("integrator_dt", integrator_dt)
        require(integrator_dt <= dt, "integrator_dt", integrator_dt, f"<= dt = {dt}")
        self.horizon = positive_integer("horizon", horizon)
        self.obs_noise_std = nonnegative("obs_noise_std", obs_noise_std)
        reward_width = positive("reward_width", reward_width)
        start_xy_std = nonnegative("start_xy_std", start_xy_std)
        start_yaw_std = nonnegative("start_yaw_std", start_yaw_std)
        self.target = finite_array("target", target, 3, "3 finite numbers")
        self.render_mode = check_render_mode(render_mode, self.metadata["render_modes"])

        self.n_substeps = n_substeps(self.dt, integrator_dt)
        self.integrator_dt = self.dt / self.n_substeps
        self.metadata = {**self.metadata, "render_fps": max(1, round(1.0 / self.dt))}

        self.start_mean = np.zeros(OBS_DIM)
        self.start_std = np.zeros(OBS_DIM)
        self.start_std[[0, 1]] = start_xy_std
        self.start_std[5] = start_yaw_std
        self.reward_spec = self._make_reward_spec(self.target, reward_width)

        self.action_space = spaces.Box(-1.0, 1.0, shape=(ACTION_DIM,), dtype=np.float64)
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(OBS_DIM,), dtype=np.float64)

        # Internal state (16 floats): p (3), η (3), v world (3), ω body (3), actuators (4).
        self._s: list[float] | None = None
        self._steps = 0
        self._autopilot: Autopilot | None = None

    # ---- reward ------------------------------------------------------------------------------
    @staticmethod
    def _make_reward_spec(target: np.ndarray, width: float) -> SaturatingReward:
        """r = exp(−‖p − p*‖² / (2 width²)): W = diag(1, 1, 1, 0, …, 0), no angle dimensions."""
        weight = np.zeros((OBS_DIM, OBS_DIM))
        weight[list(POSITION_DIMS), list(POSITION_DIMS)] = 1.0
        full_target = np.zeros(OBS_DIM)
        full_target[list(POSITION_DIMS)] = target
        return SaturatingReward(state_dim=OBS_DIM, angle_dims=(), target=full_target, weight=weight, width=width)

    # ---- vehicle interface -------------------------------------------------------------------
    @abstractmethod
    def _wrench(
        self,
        height: float,
        attitude: tuple[float, float, float],
        body_velocity: tuple[float, float, float],
        body_rates: tuple[float, float, float],
        actuators: Sequence[float],
        command: tuple[float, float, float, float],
    ) -> tuple[float, float, float, float, float, float, list[float]]:
        """Body force (Fx, Fy, Fz), body torque (τx, τy, τz) and the actuators' time derivative.

        `command` is (collective in [−1, 1], roll, pitch and yaw set-points in rad); the inner
        attitude loop runs here, in continuous time.
        """

    @abstractmethod
    def _rest_actuators(self) -> list[float]:
        """Actuator state of a vehicle at rest with zero thrust (the reset state)."""

    @abstractmethod
    def _hover_actuators(self) -> list[float]:
        """Actuator state holding the weight level out of ground effect (`options["state"]`)."""

    def collective_for_thrust(self, thrust: float) -> float:
        """The collective whose steady rotor thrust out of ground effect is `thrust` (N).

        The inverse of the collective law T = (1 + c) / 2 · `max_thrust` of both vehicles.
        """
        return 2.0 * thrust / self.max_thrust - 1.0

    @property
    @abstractmethod
    def trim_roll(self) -> float:
        """Steady roll angle (rad) that holds position in hover (0 without a lateral bias)."""

    @abstractmethod
    def _drawing(self) -> list[tuple[np.ndarray, _render.Color, float]]:
        """Polylines `N x 3` in body coordinates (gear bottom at the origin), colour, width (m)."""

    # ---- physics -----------------------------------------------------------------------------
    def thrust_factor(self, height: float | np.ndarray) -> float | np.ndarray:
        """Ground-effect factor of this vehicle with its gear at `height` (m); 1 when disabled."""
        if not self.ground_effect:
            return np.ones_like(height, dtype=float) if np.ndim(height) else 1.0
        return ground_effect_factor(np.asarray(height) + self.rotor_height, self.rotor_radius)

    def _ground_factor(self, height: float) -> float:
        """Scalar :func:`ground_effect_factor` in plain floats (the integrator's hot path)."""
        if not self.ground_effect:
            return 1.0
        radius = self.rotor_radius
        z_r = max(height + self.rotor_height, GROUND_EFFECT_MIN_HEIGHT_RATIO * radius)
        return min(1.0 / (1.0 - (radius / (4.0 * z_r)) ** 2), GROUND_EFFECT_MAX_FACTOR)

    def _derivative(self, s: Sequence[float], command: tuple[float, float, float, float]) -> list[float]:
        """d/dt of the 16-float internal state (plain floats: 3-vectors are too small for numpy)."""
        _, _, z, phi, theta, psi, vx, vy, vz, p, q, r = s[:12]
        sphi, cphi = math.sin(phi), math.cos(phi)
        sth, cth = math.sin(theta), math.cos(theta)
        spsi, cpsi = math.sin(psi), math.cos(psi)
        # R = R_z(ψ) R_y(θ) R_x(φ), body to world.
        r11, r12, r13 = cpsi * cth, cpsi * sth * sphi - spsi * cphi, cpsi * sth * cphi + spsi * sphi
        r21, r22, r23 = spsi * cth, spsi * sth * sphi + cpsi * cphi, spsi * sth * cphi - cpsi * sphi
        r31, r32, r33 = -sth, cth * sphi, cth * cphi
        body_velocity = (
            r11 * vx + r21 * vy + r31 * vz,
            r12 * vx + r22 * vy + r32 * vz,
            r13 * vx + r23 * vy + r33 * vz,
        )
        fx, fy, fz, tx, ty, tz, actuator_rates = self._wrench(
            z, (phi, theta, psi), body_velocity, (p, q, r), s[12:], command
        )
        m = self.mass
        jx, jy, jz = self.inertia
        # Euler-angle kinematics η̇ = E(η) ω (ZYX).
        q_s_r_c = q * sphi + r * cphi
        return [
            vx,
            vy,
            vz,
            p + q_s_r_c * sth / cth,
            q * cphi - r * sphi,
            q_s_r_c / cth,
            (r11 * fx + r12 * fy + r13 * fz) / m,
            (r21 * fx + r22 * fy + r23 * fz) / m,
            (r31 * fx + r32 * fy + r33 * fz) / m - GRAVITY,
            (tx - (jz - jy) * q * r) / jx,
            (ty - (jx - jz) * r * p) / jy,
            (tz - (jy - jx) * p * q) / jz,
            *actuator_rates,
        ]

    def _integrate(self, s: list[float], command: tuple[float, float, float, float]) -> list[float]:
        """RK4 over one control period with the command held, ground contact after each sub-step."""
        for _ in range(self.n_substeps):
            new = rk4_step(self._derivative, s, self.integrator_dt, command)
            if new[2] <= 0.0:
                # At rest on the ground: hold x, y and yaw, level, no motion; actuators run on.
                new[:12] = [s[0], s[1], 0.0, 0.0, 0.0, s[5], 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
            s = new
        return s

    @staticmethod
    def _euler_rates(s: Sequence[float]) -> tuple[float, float, float]:
        """(φ̇, θ̇, ψ̇) = E(η) ω of the internal state."""
        phi, theta = s[3], s[4]
        p, q, r = s[9:12]
        sphi, cphi, cth = math.sin(phi), math.cos(phi), math.cos(theta)
        q_s_r_c = q * sphi + r * cphi
        return (p + q_s_r_c * math.sin(theta) / cth, q * cphi - r * sphi, q_s_r_c / cth)

    @staticmethod
    def _body_rates(state: np.ndarray) -> list[float]:
        """ω = E(η)⁻¹ η̇ of a 12-D state."""
        phi, theta = float(state[3]), float(state[4])
        dphi, dtheta, dpsi = (float(v) for v in state[9:12])
        sphi, cphi, sth, cth = math.sin(phi), math.cos(phi), math.sin(theta), math.cos(theta)
        return [
            dphi - sth * dpsi,
            cphi * dtheta + sphi * cth * dpsi,
            -sphi * dtheta + cphi * cth * dpsi,
        ]

    def _state12(self) -> np.ndarray:
        assert self._s is not None
        return np.array([*self._s[:9], *self._euler_rates(self._s)], dtype=float)

    @property
    def state(self) -> np.ndarray | None:
        """The noise-free 12-D state [x, y, z, φ, θ, ψ, ẋ, ẏ, ż, φ̇, θ̇, ψ̇] (None before reset)."""
        return None if self._s is None else self._state12()

    @property
    def actuator_state(self) -> np.ndarray | None:
        """The four hidden actuator states (not part of the observation; None before reset)."""
        return None if self._s is None else np.array(self._s[12:], dtype=float)

    def command(self, action: np.ndarray) -> tuple[float, float, float, float]:
        """The clipped action as (collective, roll, pitch, yaw set-points in rad)."""
        a = np.clip(np.asarray(action, dtype=float).reshape(-1), -1.0, 1.0)
        return (
            float(a[0]),
            MAX_TILT_SETPOINT * float(a[1]),
            MAX_TILT_SETPOINT * float(a[2]),
            MAX_YAW_SETPOINT * float(a[3]),
        )

    # ---- reference controller ----------------------------------------------------------------
    def autopilot(self, obs: np.ndarray) -> np.ndarray:
        """The default :class:`Autopilot` of this vehicle applied to `obs` (an action)."""
        if self._autopilot is None:
            self._autopilot = Autopilot(self)
        return self._autopilot(obs)

    # ---- gymnasium API -----------------------------------------------------------------------
    def _observe(self) -> np.ndarray:
        obs = self._state12()
        if self.obs_noise_std > 0:
            obs += self.obs_noise_std * self.np_random.standard_normal(OBS_DIM)
        return obs

    def _info(self) -> dict[str, Any]:
        assert self._s is not None
        return {"state": self._state12(), "actuators": np.array(self._s[12:], dtype=float)}

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start at rest on the ground, x, y, ψ ~ N(0, std²); or at `options["state"]` (12-D).

        From `options["state"]` the actuators start in hover trim if z > 0, at rest otherwise; a
        state with z < 0 is refused.
        """
        super().reset(seed=seed)
        state = state_option(options, OBS_DIM, condition=lambda s: s[2] >= 0, rule="z >= 0")
        if state is not None:
            actuators = self._hover_actuators() if state[2] > 0 else self._rest_actuators()
            self._s = [*(float(v) for v in state[:9]), *self._body_rates(state), *actuators]
        else:
            state = self.start_mean + self.start_std * self.np_random.standard_normal(OBS_DIM)
            self._s = [*(float(v) for v in state[:9]), 0.0, 0.0, 0.0, *self._rest_actuators()]
        self._steps = 0
        return self._observe(), self._info()

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Hold the action for `dt`; the reward scores the noise-free successor state."""
        if self._s is None:
            raise gymnasium.error.ResetNeeded("call reset() before step()")
        a = action_vector(action, ACTION_DIM)
        self._s = self._integrate(self._s, self.command(a))
        self._steps += 1
        reward = float(self.reward_spec(self._state12()))
        truncated = self._steps >= self.horizon
        return self._observe(), reward, False, truncated, self._info()

    # ---- rendering ---------------------------------------------------------------------------
    def render(self) -> np.ndarray | None:
        """An `H x W x 3` `uint8` frame: top view (x–y, left) and side view (x–z, right).

        The vehicle is drawn with its attitude (its front in orange; to scale, times
        `RENDER_SCALE`), the target as a red cross, the ground in brown in the side view, a 1 m
        grid in both. The views span x, y in [−2.5, 1.5] m and z in [−0.4, 3.6] m.
        """
        if self.render_mode is None:
            _render.warn_no_render_mode()
            return None
        s = self._s
        if s is None:
            s = [0.0] * (OBS_DIM + N_ACTUATORS)
        phi, theta, psi = s[3:6]
        rot = _rotation(phi, theta, psi)
        position = np.array(s[:3])
        polylines = [
            (self.RENDER_SCALE * pts @ rot.T + position, color, width) for pts, color, width in self._drawing()
        ]
        views = []
        for axes, y_range in (((0, 1), _RENDER_XY_RANGE), ((0, 2), _RENDER_Z_RANGE)):
            canvas = _render.Canvas(_RENDER_VIEW_WIDTH_PX, _RENDER_XY_RANGE, y_range, _render.SKY)
            lo, hi = y_range
            for g in np.arange(math.ceil(_RENDER_XY_RANGE[0]), _RENDER_XY_RANGE[1] + 1e-9, _RENDER_GRID_STEP):
                canvas.line((g, lo), (g, hi), 0.01, _render.LIGHT_GREY)
            for g in np.arange(math.ceil(lo), hi + 1e-9, _RENDER_GRID_STEP):
                canvas.line((_RENDER_XY_RANGE[0], g), (_RENDER_XY_RANGE[1], g), 0.01, _render.LIGHT_GREY)
            if axes[1] == 2:
                canvas.polygon(
                    np.array(
                        [
                            [_RENDER_XY_RANGE[0], lo],
                            [_RENDER_XY_RANGE[1], lo],
                            [_RENDER_XY_RANGE[1], 0.0],
                            [_RENDER_XY_RANGE[0], 0.0],
                        ]
                    ),
                    _render.BROWN,
                )
            tx, ty = self.target[axes[0]], self.target[axes[1]]
            arm = _RENDER_TARGET_ARM
            canvas.line((tx - arm, ty - arm), (tx + arm, ty + arm), _RENDER_LINE, _render.RED)
            canvas.line((tx - arm, ty + arm), (tx + arm, ty - arm), _RENDER_LINE, _render.RED)
            for pts, color, width in polylines:
                canvas.polyline(pts[:, list(axes)], width, color)
            views.append(canvas.frame())
        height = max(v.shape[0] for v in views)
        gap = np.full((height, _RENDER_GAP_PX, 3), 255, dtype=np.uint8)
        padded = [np.concatenate([v, np.full((height - v.shape[0], v.shape[1], 3), 255, np.uint8)]) for v in views]
        return np.concatenate([padded[0], gap, padded[1]], axis=1)

    def close(self) -> None:
        """Nothing to release (no window is ever opened)."""


def _rotation(phi: float, theta: float, psi: float) -> np.ndarray:
    """R = R_z(ψ) R_y(θ) R_x(φ), `3 x 3`, body to world."""
    sphi, cphi = math.sin(phi), math.cos(phi)
    sth, cth = math.sin(theta), math.cos(theta)
    spsi, cpsi = math.sin(psi), math.cos(psi)
    return np.array(
        [
            [cpsi * cth, cpsi * sth * sphi - spsi * cphi, cpsi * sth * cphi + spsi * sphi],
            [spsi * cth, spsi * sth * sphi + cpsi * cphi, spsi * sth * cphi - cpsi * sphi],
            [-sth, cth * sphi, cth * cphi],
        ]
    )


def _circle(center: Sequence[float], radius: float) -> np.ndarray:
    """A closed horizontal circle `N x 3` in body coordinates."""
    t = np.linspace(0.0, 2.0 * math.pi, _RENDER_CIRCLE_POINTS + 1)
    return np.stack(
        [
            center[0] + radius * np.cos(t),
            center[1] + radius * np.sin(t),
            np.full_like(t, center[2]),
        ],
        axis=-1,
    )


class QuadcopterEnv(AircraftEnv):
    r"""
    ## Description

    Take-off and hover of a ~0.5 kg X-frame quadcopter with AscTec Hummingbird-like figures, the
    source task of the paper's Section 5.3: start on the ground at the origin, fly to
    `target` = (−1, −1, 1.5) m and hold it. A rigid body (mass `mass`, diagonal inertia
    `inertia`) carries four rotors on arms of length `arm_length` at ±45° from the nose, spinning
    alternately; rotor i makes thrust k_f ω_i² along body z and drag torque ±k_m ω_i² about it.

    The action is turned into rotor speeds by the vehicle itself, in continuous time:

    - the collective sets the total thrust T = (1 + c) / 2 · `max_thrust` (0 at c = −1, hover at
      c ≈ 0 for the default mass, `max_thrust` = 2 m g);
    - an inner attitude PD gives the torques τ = J (K_p (η_ref − η) − K_d ω);
    - the X-frame mixing splits (T, τ) into four rotor thrusts in [0, k_f ω_max²] with thrust
      priority (roll / pitch, then yaw torque are shrunk until every rotor is in range, so the
      total thrust is always the collective's; near zero collective the attitude loop therefore
      loses authority, as a real quadcopter does), and each rotor speed follows its command
      ω_cmd = √(f / k_f) with a first-order motor lag of `motor_time_constant`.

    Forces: rotor thrust × the Cheeseman–Bennett ground-effect factor of rotor radius
    `rotor_radius` at height z + `rotor_height` (it fades above about 0.3 m), quadratic drag
    −c_i |u_i| u_i along body axes, gravity. On the ground the vehicle rests (no sinking,
    sliding or tilting) until the thrust exceeds its weight.

    The four rotor speeds are hidden states: the observation is not Markov on its own (a
    20 ms lag, short against the 0.1 s step, so a GP model on the observation sees it as noise).

    ## Action Space

    An `ndarray` with shape `(4,)` in [−1, 1]; actions outside the box are clipped.

    | Num | Action                                          | Min  | Max |
    |-----|-------------------------------------------------|------|-----|
    | 0   | collective: thrust (1 + c) / 2 · `max_thrust`  | -1.0 | 1.0 |
    | 1   | roll set-point / 0.35 rad                       | -1.0 | 1.0 |
    | 2   | pitch set-point / 0.35 rad                      | -1.0 | 1.0 |
    | 3   | yaw set-point / (π/2) rad                       | -1.0 | 1.0 |

    ## Observation Space

    An `ndarray` with shape `(12,)` (float64), the noise-free state plus optional Gaussian noise
    of std `obs_noise_std`; world frame z up, ZYX Euler angles (not wrapped), every bound
    infinite.

    | Num | Observation                | Num | Observation                   |
    |-----|----------------------------|-----|-------------------------------|
    | 0   | x (m)                      | 6   | ẋ (m/s)                       |
    | 1   | y (m)                      | 7   | ẏ (m/s)                       |
    | 2   | z, height of the gear (m)  | 8   | ż (m/s)                       |
    | 3   | roll φ (rad)               | 9   | φ̇ (rad/s)                     |
    | 4   | pitch θ (rad)              | 10  | θ̇ (rad/s)                     |
    | 5   | yaw ψ (rad)                | 11  | ψ̇ (rad/s)                     |

    ## Rewards

    The saturating reward of Eq. 13 with PILCO's cost width σ_c = `reward_width`:
    *r = exp(−‖p − p*‖² / (2 σ_c²))*, p = (x, y, z), p* = `target`; `step` scores the noise-free
    successor state. The same reward is `reward_spec`, a `SaturatingReward` with no angle
    dimensions, W = diag(1, 1, 1, 0, …, 0) and target (p*, 0, …, 0).

    ## Starting State

    At rest on the ground at the origin, rotors stopped, with x, y ~ N(0, `start_xy_std`²) and
    ψ ~ N(0, `start_yaw_std`²) (`start_mean`, `start_std`). `reset(options={"state": s})`
    starts from the 12-D state `s` (layout of the observation, z >= 0) instead: the hidden rotor
    speeds start in hover trim if z > 0 and stopped if z = 0.

    ## Episode Truncation

    The episode never terminates (a landing or a hard touch-down ends at rest on the ground); it
    is truncated after `horizon` steps (default 200, i.e. 20 s).

    ## Arguments

    - `mass`: vehicle mass in kg (default 0.5).
    - `inertia`: principal moments (J_x, J_y, J_z) in kg m² (default (3.65e−3, 3.68e−3, 7.03e−3)).
    - `arm_length`: centre-to-rotor distance in m (default 0.17).
    - `thrust_coefficient`: k_f in N s² (default 5.57e−6).
    - `torque_coefficient`: k_m in N m s² (default 1.36e−7).
    - `motor_time_constant`: rotor-speed lag in s (default 0.02).
    - `max_rotor_speed`: ω_max in rad/s (default 800, 3.6 N per rotor).
    - `max_thrust`: total thrust in N commanded by collective +1 (default 2 × 0.5 × 9.81).
    - `drag_coefficient`: quadratic drag (c_x, c_y, c_z) in N s²/m² along body axes
      (default (0.05, 0.05, 0.1)).
    - `rotor_radius`: R in m (default 0.1), for the ground effect.
    - `rotor_height`: rotor plane above the gear in m (default 0.06).
    - `ground_effect`: apply the ground effect (default True).
    - `attitude_kp`, `attitude_kd`: inner-loop gains (roll, pitch, yaw) in rad/s² per rad and
      per rad/s (default (225, 225, 25) and (21, 21, 7)).
    - `dt`: control period in s (default 0.1).
    - `integrator_dt`: largest RK4 sub-step in s (default 0.005); `dt` is split into
      ceil(`dt` / `integrator_dt`) equal sub-steps.
    - `horizon`: steps until truncation (default 200).
    - `obs_noise_std`: std of the Gaussian observation noise (default 0).
    - `reward_width`: σ_c in m (default 0.25).
    - `start_xy_std`: std of the start position x, y in m (default 0.1).
    - `start_yaw_std`: std of the start yaw ψ in rad (default 0.1).
    - `target`: (x*, y*, z*) in m (default (−1, −1, 1.5)).
    - `render_mode`: `None` or `"rgb_array"`.

    ```python
    >>> import gymnasium, envs
    >>> env = gymnasium.make("qtl/Quadcopter-v0", mass=0.6)
    >>> obs, info = env.reset(seed=0)
    >>> obs, reward, terminated, truncated, info = env.step(env.unwrapped.autopilot(obs))
    ```
    """

    AUTOPILOT_GAINS: ClassVar[dict[str, float]] = QUAD_AUTOPILOT_GAINS
    RENDER_SCALE: ClassVar[float] = QUAD_RENDER_SCALE

    def __init__(
        self,
        mass: float = QUAD_MASS,
        inertia: Sequence[float] = QUAD_INERTIA,
        arm_length: float = QUAD_ARM_LENGTH,
        thrust_coefficient: float = QUAD_THRUST_COEFFICIENT,
        torque_coefficient: float = QUAD_TORQUE_COEFFICIENT,
        motor_time_constant: float = QUAD_MOTOR_TIME_CONSTANT,
        max_rotor_speed: float = QUAD_MAX_ROTOR_SPEED,
        max_thrust: float = QUAD_MAX_THRUST,
        drag_coefficient: Sequence[float] = QUAD_DRAG_COEFFICIENT,
        rotor_radius: float = QUAD_ROTOR_RADIUS,
        rotor_height: float = QUAD_ROTOR_HEIGHT,
        ground_effect: bool = True,
        attitude_kp: Sequence[float] = QUAD_ATTITUDE_KP,
        attitude_kd: Sequence[float] = QUAD_ATTITUDE_KD,
        dt: float = DEFAULT_DT,
        integrator_dt: float = DEFAULT_INTEGRATOR_DT,
        horizon: int = DEFAULT_HORIZON,
        obs_noise_std: float = DEFAULT_OBS_NOISE_STD,
        reward_width: float = DEFAULT_REWARD_WIDTH,
        start_xy_std: float = DEFAULT_START_XY_STD,
        start_yaw_std: float = DEFAULT_START_YAW_STD,
        target: Sequence[float] = DEFAULT_TARGET,
        render_mode: str | None = None,
    ) -> None:
        super().__init__(
            mass=mass,
            inertia=inertia,
            rotor_radius=rotor_radius,
            rotor_height=rotor_height,
            max_thrust=max_thrust,
            ground_effect=ground_effect,
            dt=dt,
            integrator_dt=integrator_dt,
            horizon=horizon,
            obs_noise_std=obs_noise_std,
            reward_width=reward_width,
            start_xy_std=start_xy_std,
            start_yaw_std=start_yaw_std,
            target=target,
            render_mode=render_mode,
        )
        self.arm_length = positive("arm_length", arm_length)
        self.thrust_coefficient = positive("thrust_coefficient", thrust_coefficient)
        self.torque_coefficient = nonnegative("torque_coefficient", torque_coefficient)
        self.motor_time_constant = positive("motor_time_constant", motor_time_constant)
        self.max_rotor_speed = positive("max_rotor_speed", max_rotor_speed)
        self.drag_coefficient = finite_tuple("drag_coefficient", drag_coefficient, 3, positive=False)
        self.attitude_kp = finite_tuple("attitude_kp", attitude_kp, 3, positive=False)
        self.attitude_kd = finite_tuple("attitude_kd", attitude_kd, 3, positive=False)
        # Motors on the diagonals at (±d, ±d), d = arm / √2; spin directions +, −, +, −.
        self._arm_projection = self.arm_length / math.sqrt(2.0)
        self._yaw_per_thrust = self.torque_coefficient / self.thrust_coefficient  # κ = k_m / k_f, m
        self._max_rotor_thrust = self.thrust_coefficient * self.max_rotor_speed**2

    def _wrench(
        self,
        height: float,
        attitude: tuple[float, float, float],
        body_velocity: tuple[float, float, float],
        body_rates: tuple[float, float, float],
        actuators: Sequence[float],
        command: tuple[float, float, float, float],
    ) -> tuple[float, float, float, float, float, float, list[float]]:
        phi, theta, psi = attitude
        p, q, r = body_rates
        collective, phi_ref, theta_ref, psi_ref = command
        jx, jy, jz = self.inertia
        kp, kd = self.attitude_kp, self.attitude_kd
        kf, d, kappa = self.thrust_coefficient, self._arm_projection, self._yaw_per_thrust
        # Inner attitude loop and X-frame mixing: motors 0..3 at (+d, +d), (−d, +d), (−d, −d),
        # (+d, −d), so τx = d (f0 + f1 − f2 − f3), τy = d (−f0 + f1 + f2 − f3),
        # τz = κ (f0 − f1 + f2 − f3), T = Σ f; the inverse below solves for f.
        f_max, tau_m = self._max_rotor_thrust, self.motor_time_constant
        thrust_share = min(0.25 * 0.5 * (1.0 + collective) * self.max_thrust, f_max)
        roll_share = jx * (kp[0] * (phi_ref - phi) - kd[0] * p) / (4.0 * d)
        pitch_share = jy * (kp[1] * (theta_ref - theta) - kd[1] * q) / (4.0 * d)
        yaw_share = jz * (kp[2] * (psi_ref - psi) - kd[2] * r) / (4.0 * kappa) if kappa > 0 else 0.0
        # Thrust-priority desaturation: shrink roll / pitch, then yaw, to what fits in every
        # rotor's range, so the rotors never clip and the total thrust is the collective's.
        margin = min(thrust_share, f_max - thrust_share)
        tilt_demand = abs(roll_share) + abs(pitch_share)
        if tilt_demand > margin:
            roll_share *= margin / tilt_demand
            pitch_share *= margin / tilt_demand
            tilt_demand = margin
        yaw_share = _clip(yaw_share, margin - tilt_demand)
        commanded = (
            thrust_share + roll_share - pitch_share + yaw_share,
            thrust_share + roll_share + pitch_share - yaw_share,
            thrust_share - roll_share + pitch_share + yaw_share,
            thrust_share - roll_share - pitch_share - yaw_share,
        )
        rates = [
            (math.sqrt(min(max(f, 0.0), f_max) / kf) - w) / tau_m for f, w in zip(commanded, actuators, strict=True)
        ]
        w0, w1, w2, w3 = (w * w for w in actuators)
        gain = kf * self._ground_factor(height)
        f0, f1, f2, f3 = gain * w0, gain * w1, gain * w2, gain * w3
        u, v, w = body_velocity
        cx, cy, cz = self.drag_coefficient
        return (
            -cx * abs(u) * u,
            -cy * abs(v) * v,
            f0 + f1 + f2 + f3 - cz * abs(w) * w,
            d * (f0 + f1 - f2 - f3),
            d * (-f0 + f1 + f2 - f3),
            self.torque_coefficient * (w0 - w1 + w2 - w3),
            rates,
        )

    def _rest_actuators(self) -> list[float]:
        return [0.0] * N_ACTUATORS

    def _hover_actuators(self) -> list[float]:
        return [math.sqrt(self.mass * GRAVITY / (N_ACTUATORS * self.thrust_coefficient))] * N_ACTUATORS

    @property
    def trim_roll(self) -> float:
        return 0.0

    def _drawing(self) -> list[tuple[np.ndarray, _render.Color, float]]:
        d, h, radius = self._arm_projection, self.rotor_height, self.rotor_radius
        hub = (0.0, 0.0, 0.5 * h)
        parts: list[tuple[np.ndarray, _render.Color, float]] = [
            (np.array([[0.0, 0.0, 0.0], hub]), _render.DARK_GREY, _RENDER_LINE),
        ]
        for sx, sy in ((-1, 1), (-1, -1), (1, 1), (1, -1)):  # rear first, front drawn on top
            color = _render.ORANGE if sx > 0 else _render.DARK_GREY
            motor = (sx * d, sy * d, h)
            parts.append((np.array([hub, motor]), color, _RENDER_LINE))
            parts.append((_circle(motor, radius), _render.BLUE, 0.5 * _RENDER_LINE))
        return parts


class HelicopterEnv(AircraftEnv):
    r"""
    ## Description

    Take-off and hover of a small single-rotor helicopter, the target task of the paper's
    Section 5.3: start on the ground at the origin, fly to `target` = (−1, −1, 1.5) m and hold
    it. A near-hover model in the style of the XCell Tempest model of Abbeel et al. (2006), put
    on a rigid body of mass `mass` and inertia `inertia`.

    The forces and moments:

    - main-rotor thrust along body z, linear in the lagged collective pitch,
      T = (1 + δ_col) / 2 · `max_thrust` (hover at δ_col ≈ 0 for the default mass), times the
      Cheeseman–Bennett ground-effect factor of the large rotor (R = 0.69 m: it reaches ~1.4 m);
    - linear damping of the body velocities (u̇, v̇, ẇ ∋ −0.18 u, −0.43 v, −0.49 w) and of the
      body rates (ṗ, q̇, ṙ ∋ −12.8 p, −10.1 q, −8.2 r), `velocity_damping` and `rate_damping`;
    - cyclic moments proportional to the lagged lateral / longitudinal cyclic, `cyclic_moment`;
    - a tail rotor at `tail_arm` behind the shaft whose torque `tail_moment` × δ_ped comes with a
      side force −`tail_moment` δ_ped / `tail_arm` along body y;
    - the main rotor's reaction torque −`main_rotor_torque_ratio` × T about body z: more
      collective yaws the helicopter until the tail rotor pushes back, and that push is the
      tail-rotor side force, so holding position needs a steady roll of
      −atan(`main_rotor_torque_ratio` / `tail_arm`) ≈ −3.6° (`trim_roll`).

    The inner loop is a flybarless / heading-hold controller: cyclic and pedal commands
    δ = clip(K_p (η_ref − η) − K_d ω, ±1) for roll, pitch and yaw; all four channels (collective
    included) reach the rotor through a first-order rotor / flapping lag of
    `rotor_time_constant` (0.08 s). The PD yaw loop leaves a small heading error proportional to
    the collective (the collective → yaw coupling).

    The four lagged actuator states are hidden: the observation is not Markov on its own (an
    80 ms lag against the 0.1 s step — a GP model on the observation sees part of it as noise).

    ## Action Space

    An `ndarray` with shape `(4,)` in [−1, 1]; actions outside the box are clipped.

    | Num | Action                                              | Min  | Max |
    |-----|-----------------------------------------------------|------|-----|
    | 0   | collective: thrust (1 + δ_col) / 2 · `max_thrust`   | -1.0 | 1.0 |
    | 1   | roll set-point / 0.35 rad                           | -1.0 | 1.0 |
    | 2   | pitch set-point / 0.35 rad                          | -1.0 | 1.0 |
    | 3   | yaw set-point / (π/2) rad                           | -1.0 | 1.0 |

    ## Observation Space

    As :class:`QuadcopterEnv`: `(12,)` float64, [x, y, z, φ, θ, ψ, ẋ, ẏ, ż, φ̇, θ̇, ψ̇] (world
    frame z up, ZYX Euler angles not wrapped, z the height of the skids), plus optional Gaussian
    noise of std `obs_noise_std`; every bound infinite.

    ## Rewards

    As :class:`QuadcopterEnv`: *r = exp(−‖p − p*‖² / (2 σ_c²))* on the noise-free successor
    state, declared as `reward_spec`.

    ## Starting State

    At rest on the ground at the origin, collective at −1 (no thrust), cyclic and pedal centred,
    with x, y ~ N(0, `start_xy_std`²) and ψ ~ N(0, `start_yaw_std`²) (`start_mean`,
    `start_std`). `reset(options={"state": s})` starts from the 12-D state `s` (layout of the
    observation, z >= 0) instead: the hidden actuators start in hover trim (collective holding
    the weight, pedal against the main-rotor torque) if z > 0 and at rest if z = 0.

    ## Episode Truncation

    The episode never terminates; it is truncated after `horizon` steps (default 200, 20 s).

    ## Arguments

    - `mass`: vehicle mass in kg (default 5.0).
    - `inertia`: principal moments (J_x, J_y, J_z) in kg m² (default (0.18, 0.34, 0.28)).
    - `max_thrust`: main-rotor thrust in N at collective +1 (default 2 × 5 × 9.81).
    - `velocity_damping`: (X_u, Y_v, Z_w) in 1/s (default (0.18, 0.43, 0.49)).
    - `rate_damping`: (L_p, M_q, N_r) in 1/s (default (12.8, 10.1, 8.2)).
    - `rotor_time_constant`: rotor / flapping lag in s (default 0.08).
    - `cyclic_moment`: roll and pitch moment in N m per unit cyclic (default (11.5, 21.8)).
    - `tail_moment`: yaw moment in N m per unit pedal (default 11.2).
    - `tail_arm`: tail-rotor distance behind the main shaft in m (default 0.8).
    - `main_rotor_torque_ratio`: main-rotor reaction torque per newton of thrust in m
      (default 0.05).
    - `rotor_radius`: R in m (default 0.69); `rotor_height`: hub above the skids in m
      (default 0.35); `ground_effect`: apply the ground effect (default True).
    - `attitude_kp`, `attitude_kd`: inner-loop gains (roll, pitch, yaw) in unit command per rad
      and per rad/s (default (1, 1, 2) and (0.05, 0.05, 0.1)).
    - `dt` (0.1 s), `integrator_dt` (0.005 s), `horizon` (200), `obs_noise_std` (0),
      `reward_width` (0.25 m), `start_xy_std` (0.1 m), `start_yaw_std` (0.1 rad), `target`
      ((−1, −1, 1.5) m), `render_mode` (`None` or `"rgb_array"`): as :class:`QuadcopterEnv`.

    ```python
    >>> import gymnasium, envs
    >>> env = gymnasium.make("qtl/Helicopter-v0", mass=5.5)
    ```
    """

    AUTOPILOT_GAINS: ClassVar[dict[str, float]] = HELI_AUTOPILOT_GAINS

    def __init__(
        self,
        mass: float = HELI_MASS,
        inertia: Sequence[float] = HELI_INERTIA,
        max_thrust: float = HELI_MAX_THRUST,
        velocity_damping: Sequence[float] = HELI_VELOCITY_DAMPING,
        rate_damping: Sequence[float] = HELI_RATE_DAMPING,
        rotor_time_constant: float = HELI_ROTOR_TIME_CONSTANT,
        cyclic_moment: Sequence[float] = HELI_CYCLIC_MOMENT,
        tail_moment: float = HELI_TAIL_MOMENT,
        tail_arm: float = HELI_TAIL_ARM,
        main_rotor_torque_ratio: float = HELI_MAIN_ROTOR_TORQUE_RATIO,
        rotor_radius: float = HELI_ROTOR_RADIUS,
        rotor_height: float = HELI_ROTOR_HEIGHT,
        ground_effect: bool = True,
        attitude_kp: Sequence[float] = HELI_ATTITUDE_KP,
        attitude_kd: Sequence[float] = HELI_ATTITUDE_KD,
        dt: float = DEFAULT_DT,
        integrator_dt: float = DEFAULT_INTEGRATOR_DT,
        horizon: int = DEFAULT_HORIZON,
        obs_noise_std: float = DEFAULT_OBS_NOISE_STD,
        reward_width: float = DEFAULT_REWARD_WIDTH,
        start_xy_std: float = DEFAULT_START_XY_STD,
        start_yaw_std: float = DEFAULT_START_YAW_STD,
        target: Sequence[float] = DEFAULT_TARGET,
        render_mode: str | None = None,
    ) -> None:
        super().__init__(
            mass=mass,
            inertia=inertia,
            rotor_radius=rotor_radius,
            rotor_height=rotor_height,
            max_thrust=max_thrust,
            ground_effect=ground_effect,
            dt=dt,
            integrator_dt=integrator_dt,
            horizon=horizon,
            obs_noise_std=obs_noise_std,
            reward_width=reward_width,
            start_xy_std=start_xy_std,
            start_yaw_std=start_yaw_std,
            target=target,
            render_mode=render_mode,
        )
        self.velocity_damping = finite_tuple("velocity_damping", velocity_damping, 3, positive=False)
        self.rate_damping = finite_tuple("rate_damping", rate_damping, 3, positive=False)
        self.rotor_time_constant = positive("rotor_time_constant", rotor_time_constant)
        self.cyclic_moment = finite_tuple("cyclic_moment", cyclic_moment, 2, positive=True)
        self.tail_moment = positive("tail_moment", tail_moment)
        self.tail_arm = positive("tail_arm", tail_arm)
        self.main_rotor_torque_ratio = nonnegative("main_rotor_torque_ratio", main_rotor_torque_ratio)
        self.attitude_kp = finite_tuple("attitude_kp", attitude_kp, 3, positive=False)
        self.attitude_kd = finite_tuple("attitude_kd", attitude_kd, 3, positive=False)

    def _wrench(
        self,
        height: float,
        attitude: tuple[float, float, float],
        body_velocity: tuple[float, float, float],
        body_rates: tuple[float, float, float],
        actuators: Sequence[float],
        command: tuple[float, float, float, float],
    ) -> tuple[float, float, float, float, float, float, list[float]]:
        phi, theta, psi = attitude
        p, q, r = body_rates
        collective, phi_ref, theta_ref, psi_ref = command
        col, lat, lon, ped = actuators
        kp, kd = self.attitude_kp, self.attitude_kd
        # Inner loop: cyclic and pedal commands, then the rotor / flapping lag on all channels.
        lat_cmd = _clip(kp[0] * (phi_ref - phi) - kd[0] * p, 1.0)
        lon_cmd = _clip(kp[1] * (theta_ref - theta) - kd[1] * q, 1.0)
        ped_cmd = _clip(kp[2] * (psi_ref - psi) - kd[2] * r, 1.0)
        tau = self.rotor_time_constant
        rates = [
            (collective - col) / tau,
            (lat_cmd - lat) / tau,
            (lon_cmd - lon) / tau,
            (ped_cmd - ped) / tau,
        ]
        thrust = 0.5 * (1.0 + col) * self.max_thrust * self._ground_factor(height)
        tail_torque = self.tail_moment * ped
        m = self.mass
        jx, jy, jz = self.inertia
        du, dv, dw = self.velocity_damping
        dp, dq, dr = self.rate_damping
        u, v, w = body_velocity
        return (
            -m * du * u,
            -m * dv * v - tail_torque / self.tail_arm,
            thrust - m * dw * w,
            self.cyclic_moment[0] * lat - jx * dp * p,
            self.cyclic_moment[1] * lon - jy * dq * q,
            tail_torque - self.main_rotor_torque_ratio * thrust - jz * dr * r,
            rates,
        )

    def _rest_actuators(self) -> list[float]:
        return [-1.0, 0.0, 0.0, 0.0]

    def _hover_actuators(self) -> list[float]:
        weight = self.mass * GRAVITY
        return [
            self.collective_for_thrust(weight),
            0.0,
            0.0,
            self.main_rotor_torque_ratio * weight / self.tail_moment,
        ]

    @property
    def trim_roll(self) -> float:
        return -math.atan(self.main_rotor_torque_ratio / self.tail_arm)

    def _drawing(self) -> list[tuple[np.ndarray, _render.Color, float]]:
        h, radius, arm = self.rotor_height, self.rotor_radius, self.tail_arm
        skid_y, skid_x, body_z = 0.15, 0.3, 0.5 * h
        tail_z, tail_radius = 0.6 * h, 0.12
        parts: list[tuple[np.ndarray, _render.Color, float]] = []
        for side in (-skid_y, skid_y):
            parts.append(
                (
                    np.array([[-skid_x, side, 0.0], [skid_x, side, 0.0]]),
                    _render.DARK_GREY,
                    _RENDER_LINE,
                )
            )
            parts.append(
                (
                    np.array([[0.0, side, 0.0], [0.0, 0.0, body_z]]),
                    _render.DARK_GREY,
                    0.5 * _RENDER_LINE,
                )
            )
        parts += [
            (np.array([[-0.2, 0.0, body_z], [-arm, 0.0, tail_z]]), _render.DARK_GREY, _RENDER_LINE),
            (
                np.array([[-arm, 0.0, tail_z - tail_radius], [-arm, 0.0, tail_z + tail_radius]]),
                _render.BLUE,
                0.5 * _RENDER_LINE,
            ),
            (
                np.array([[-0.2, 0.0, body_z], [0.35, 0.0, body_z]]),
                _render.ORANGE,
                3.0 * _RENDER_LINE,
            ),
            (np.array([[0.0, 0.0, body_z], [0.0, 0.0, h]]), _render.DARK_GREY, _RENDER_LINE),
            (_circle((0.0, 0.0, h), radius), _render.BLUE, 0.5 * _RENDER_LINE),
        ]
        return parts


class Autopilot:
    """The reference controller of a vehicle (the "autopilot" line of the paper's Fig. 3).

    A cascaded PD: position and velocity errors give a desired world acceleration
    a = K_p (p* − p) − K_d v (horizontal part clipped to g tan 0.35 in norm, vertical part to
    ±g/2); its horizontal part, turned into the heading frame, becomes pitch and roll set-points
    θ_ref = atan(a_fwd / g), φ_ref = −atan(a_left / g) + `trim_roll` of the vehicle; the vertical
    part becomes the collective of the thrust m (g + a_z) / (cos φ cos θ) through the vehicle's
    `collective_for_thrust`; the yaw set-point is 0. It reads only the observation (plus the
    vehicle's nominal mass, collective law and trim), knows nothing of the ground effect or the
    hidden actuator lags, and holds no state, so `action = Autopilot(env)(obs)` at every step.

    Gains default to the vehicle's `AUTOPILOT_GAINS` (`kp_xy`, `kd_xy`, `kp_z`, `kd_z`, in 1/s²
    and 1/s); `target` defaults to the env's.
    """

    def __init__(
        self,
        env: gymnasium.Env,
        *,
        kp_xy: float | None = None,
        kd_xy: float | None = None,
        kp_z: float | None = None,
        kd_z: float | None = None,
        target: Sequence[float] | None = None,
    ) -> None:
        vehicle = env.unwrapped
        if not isinstance(vehicle, AircraftEnv):
            raise ValueError(f"env must be a quadcopter or helicopter env, got {type(vehicle).__name__}")
        self.vehicle = vehicle
        given = {"kp_xy": kp_xy, "kd_xy": kd_xy, "kp_z": kp_z, "kd_z": kd_z}
        gains = {k: (vehicle.AUTOPILOT_GAINS[k] if v is None else nonnegative(k, v)) for k, v in given.items()}
        self.kp_xy, self.kd_xy = gains["kp_xy"], gains["kd_xy"]
        self.kp_z, self.kd_z = gains["kp_z"], gains["kd_z"]
        self.target = vehicle.target.copy() if target is None else np.asarray(target, dtype=float)
        if self.target.shape != (3,):
            raise ValueError(f"target must be 3 numbers, got {target!r}")

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """The action `4` for the observation `12` (both float64)."""
        x, y, z, phi, theta, psi, vx, vy, vz = (float(v) for v in np.asarray(obs, dtype=float)[:9])
        ax = self.kp_xy * (self.target[0] - x) - self.kd_xy * vx
        ay = self.kp_xy * (self.target[1] - y) - self.kd_xy * vy
        az = _clip(self.kp_z * (self.target[2] - z) - self.kd_z * vz, AUTOPILOT_MAX_CLIMB_ACCEL)
        norm = math.hypot(ax, ay)
        if norm > AUTOPILOT_MAX_HORIZONTAL_ACCEL:
            ax, ay = (
                ax * AUTOPILOT_MAX_HORIZONTAL_ACCEL / norm,
                ay * AUTOPILOT_MAX_HORIZONTAL_ACCEL / norm,
            )
        a_fwd = math.cos(psi) * ax + math.sin(psi) * ay
        a_left = -math.sin(psi) * ax + math.cos(psi) * ay
        theta_ref = math.atan(a_fwd / GRAVITY)
        phi_ref = -math.atan(a_left / GRAVITY) + self.vehicle.trim_roll
        tilt = max(math.cos(phi) * math.cos(theta), AUTOPILOT_MIN_TILT_COSINE)
        thrust = self.vehicle.mass * (GRAVITY + az) / tilt
        action = np.array(
            [
                self.vehicle.collective_for_thrust(thrust),
                phi_ref / MAX_TILT_SETPOINT,
                theta_ref / MAX_TILT_SETPOINT,
                0.0,
            ]
        )
        return np.clip(action, -1.0, 1.0)
