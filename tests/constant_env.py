"""A toy gymnasium env with observation dimensions that never change, as real envs report them (registered on import).

Its id in gymnasium's ``"module:EnvId"`` form, :data:`MODULE_ID`, imports this module and so registers it in any
process, the CLI's subprocesses included.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np

SENSOR_ID = "qtl_test/ConstantSensor-v0"
MODULE_ID = f"tests.constant_env:{SENSOR_ID}"


class ConstantSensorEnv(gymnasium.Env):
    """A damped cart that reports a contact force that stays 0 and a fixed target.

    ## Description
    The action pushes the cart: v' = v + dt (u − damping v), p' = p + dt v'. The observation also holds a contact
    force that never leaves 0 and the target position, fixed for the episode: two dimensions whose change is 0.

    ## Action Space
    `Box(-1, 1, (1,))`: the push.

    ## Observation Space
    `Box(-inf, inf, (4,))`: the position p, the velocity v, the contact force (0), the target (``target``).

    ## Rewards
    −(p − target)².

    ## Starting State
    p ~ U(−0.05, 0.05), v ~ U(−0.05, 0.05); contact 0; the target.

    ## Episode Truncation
    None of its own (the task's horizon truncates).

    ## Arguments
    ``dt``, ``damping``, ``target``.
    """

    metadata = {"render_modes": []}  # noqa: RUF012  (gymnasium's convention)

    def __init__(self, dt: float = 0.2, damping: float = 0.1, target: float = 0.5) -> None:
        self.dt, self.damping, self.target = dt, damping, target
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), dtype=np.float64)
        self.observation_space = gymnasium.spaces.Box(-np.inf, np.inf, (4,), dtype=np.float64)
        self._state = np.zeros(2)

    def _obs(self) -> np.ndarray:
        """p, v, the contact force (0) and the target: `4`."""
        return np.array([*self._state, 0.0, self.target])

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        """p and v near 0."""
        super().reset(seed=seed)
        self._state = self.np_random.uniform(-0.05, 0.05, size=2)
        return self._obs(), {}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        """One step of the cart; the contact force and the target stay as they are."""
        u = float(np.clip(np.asarray(action, dtype=float).reshape(-1)[0], -1.0, 1.0))
        p, v = self._state
        v = v + self.dt * (u - self.damping * v)
        self._state = np.array([p + self.dt * v, v])
        return self._obs(), -float((self._state[0] - self.target) ** 2), False, False, {}


if SENSOR_ID not in gymnasium.registry:
    gymnasium.register(SENSOR_ID, entry_point=ConstantSensorEnv)

# A task file for it as a user writes one (docs/guide/byo-env.md), on the tiny budget.
SENSOR_TASK = f"""\
name: sensor
env:
  id: "{MODULE_ID}"
horizon: 6
angle_dims: []
policy_size: 4
start:
  mean: [0.0, 0.0, 0.0, 0.5]
  std: [0.05, 0.05, 0.01, 0.01]
reward:
  angle_dims: []
  target: [0.5, 0.0, 0.0, 0.5]
  weight: [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]
  width: 0.5
success:
  threshold: 0.2
  last_steps: 2
"""
