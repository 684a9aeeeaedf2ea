"""gymnasium's Pendulum-v1 started hanging, as a user would bring it.

Its id is ``qtl.envs.pendulum_hanging:PendulumHanging-v1``.

Importing this module registers ``PendulumHanging-v1`` (gymnasium imports it for the ``module:EnvId``
id form; :mod:`envs` does not). The dynamics, reward, observation, spaces and time limit are
Pendulum-v1's; only the reset differs: θ ~ U(π − a, π + a), θ̇ ~ U(−b, b) (θ = π hanging), the start
of PILCO's pendulum swing-up, which Pendulum-v1's reset options cannot give (they only narrow its
uniform draw around upright).
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from gymnasium.envs.classic_control.pendulum import PendulumEnv

# Half-widths of the hanging start: angle (rad) and angular speed (rad/s).
ANGLE_SPREAD = 0.1
SPEED_SPREAD = 0.1
# Pendulum-v1's own time limit (env steps).
MAX_EPISODE_STEPS = 200


class HangingStart(gymnasium.Wrapper):
    """A Pendulum-v1 whose reset puts it hanging: θ ~ U(π − a, π + a), θ̇ ~ U(−b, b), from the env's own generator."""

    def __init__(self, env: gymnasium.Env, angle_spread: float = ANGLE_SPREAD, speed_spread: float = SPEED_SPREAD):
        """Wrap a Pendulum-v1 env; the spreads a (rad) and b (rad/s) are the start's half-widths."""
        super().__init__(env)
        if not isinstance(env.unwrapped, PendulumEnv):
            raise ValueError(f"HangingStart wraps gymnasium's PendulumEnv, got {type(env.unwrapped).__name__}")
        if angle_spread < 0 or speed_spread < 0:
            raise ValueError(f"spreads must be >= 0, got {angle_spread} and {speed_spread}")
        self.angle_spread, self.speed_spread = float(angle_spread), float(speed_spread)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """The env's reset (seeding its generator), then the state moved to hanging; the observation of that state."""
        _, info = self.env.reset(seed=seed, options=options)
        pendulum = self.env.unwrapped
        rng = pendulum.np_random
        theta = np.pi + rng.uniform(-self.angle_spread, self.angle_spread)
        speed = rng.uniform(-self.speed_spread, self.speed_spread)
        pendulum.state = np.array([theta, speed])
        return pendulum._get_obs(), info


def make_pendulum_hanging(angle_spread: float = ANGLE_SPREAD, speed_spread: float = SPEED_SPREAD,
                          **kwargs: Any) -> gymnasium.Env:
    """Pendulum-v1 (its kwargs, e.g. ``g``) with the hanging start."""
    return HangingStart(PendulumEnv(**kwargs), angle_spread, speed_spread)


gymnasium.register("PendulumHanging-v1", entry_point=make_pendulum_hanging, max_episode_steps=MAX_EPISODE_STEPS)
