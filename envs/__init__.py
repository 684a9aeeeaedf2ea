"""Gymnasium environments of the paper's transfer benchmarks, registered under ``qtl/``.

Importing this package registers the ids (lazily: an env module is imported by
``gymnasium.make``, or on first access to one of its names here); it imports nothing of :mod:`qtl` but
its root package (a version string), and no torch. Installed as ``qtl.envs``: the directory is ``envs/``.

    >>> import gymnasium
    >>> from qtl import envs
    >>> env = gymnasium.make("qtl/CartPoleSwingUp-v0", pole_mass=2.0)
    >>> envs.CartPoleSwingUpEnv is type(env.unwrapped)
    True
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

import gymnasium

from qtl.envs.rewards import SaturatingReward, augment_angles

if TYPE_CHECKING:
    from qtl.envs.aircraft import Autopilot, HelicopterEnv, QuadcopterEnv, ground_effect_factor
    from qtl.envs.cartpole import CartPoleSwingUpEnv
    from qtl.envs.mountain_car import MountainCarEnv

__all__ = [
    "ENV_IDS",
    "Autopilot",
    "CartPoleSwingUpEnv",
    "HelicopterEnv",
    "MountainCarEnv",
    "QuadcopterEnv",
    "SaturatingReward",
    "augment_angles",
    "ground_effect_factor",
]

ENV_IDS: dict[str, str] = {
    "qtl/CartPoleSwingUp-v0": "qtl.envs.cartpole:CartPoleSwingUpEnv",
    "qtl/MountainCar-v0": "qtl.envs.mountain_car:MountainCarEnv",
    "qtl/Quadcopter-v0": "qtl.envs.aircraft:QuadcopterEnv",
    "qtl/Helicopter-v0": "qtl.envs.aircraft:HelicopterEnv",
}

# Public names defined in the env modules, imported on first access (PEP 562) so that
# `import qtl.envs` costs no more than gymnasium and numpy.
_LAZY: dict[str, str] = {
    "CartPoleSwingUpEnv": "qtl.envs.cartpole",
    "MountainCarEnv": "qtl.envs.mountain_car",
    "QuadcopterEnv": "qtl.envs.aircraft",
    "HelicopterEnv": "qtl.envs.aircraft",
    "Autopilot": "qtl.envs.aircraft",
    "ground_effect_factor": "qtl.envs.aircraft",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later look-ups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


for _env_id, _entry_point in ENV_IDS.items():
    if _env_id not in gymnasium.registry:
        # Each env truncates itself after its `horizon` kwarg, so no TimeLimit wrapper is added.
        gymnasium.register(id=_env_id, entry_point=_entry_point)
