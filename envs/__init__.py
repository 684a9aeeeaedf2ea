"""Gymnasium environments of the paper's transfer benchmarks, registered under ``qtl/``.

Importing this package registers the ids; it never imports :mod:`qtl`.
"""

from __future__ import annotations

import gymnasium

from envs.rewards import SaturatingReward

__all__ = ["ENV_IDS", "SaturatingReward"]

ENV_IDS: dict[str, str] = {
    "qtl/CartPoleSwingUp-v0": "envs.cartpole:CartPoleSwingUpEnv",
    "qtl/MountainCar-v0": "envs.mountain_car:MountainCarEnv",
    "qtl/Quadcopter-v0": "envs.aircraft:QuadcopterEnv",
    "qtl/Helicopter-v0": "envs.aircraft:HelicopterEnv",
}

for _env_id, _entry_point in ENV_IDS.items():
    if _env_id not in gymnasium.registry:
        # Each env truncates itself after its `horizon` kwarg, so no TimeLimit wrapper is added.
        gymnasium.register(id=_env_id, entry_point=_entry_point)
