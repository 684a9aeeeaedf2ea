"""Dataclass schema of the Hydra configuration: a typo or a wrong type fails at compose time."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from hydra.core.config_store import ConfigStore


@dataclass
class EnvConfig:
    """Which gymnasium env to make, and its constructor kwargs."""

    id: str = "qtl/CartPoleSwingUp-v0"
    kwargs: dict[str, Any] = field(default_factory=dict)


@dataclass
class ModelConfig:
    """Evidence-maximisation settings of the dynamics GP."""

    restarts: int = 3
    max_iter: int = 100


@dataclass
class TrainConfig:
    """Top level of ``qtl-train``."""

    seed: int = 0
    dtype: str = "float64"
    env: EnvConfig = field(default_factory=EnvConfig)
    angle_dims: list[int] = field(default_factory=lambda: [2])
    train_episodes: int = 3
    test_episodes: int = 1
    model: ModelConfig = field(default_factory=ModelConfig)


def register_configs() -> None:
    """Register the schema with Hydra's ConfigStore (``defaults: [train_schema, _self_]``)."""
    ConfigStore.instance().store(name="train_schema", node=TrainConfig)
