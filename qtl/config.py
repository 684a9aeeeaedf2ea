"""Dataclass schema of the Hydra configuration: a typo or a wrong type fails at compose time."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

# OmegaConf reads these annotations at run time: keep `Optional[...]` and `List`-style types
# that it understands (PEP 604 unions are not supported by OmegaConf's structured configs).


@dataclass
class StartConfig:
    """Start distribution N(mean, diag(std²)); null reads the env's ``start_mean``/``start_std``."""

    mean: Optional[list[float]] = None  # noqa: UP045
    std: Optional[list[float]] = None  # noqa: UP045


@dataclass
class RewardConfig:
    """Saturating reward (Eq. 13) for an env that does not expose ``reward_spec`` itself."""

    angle_dims: list[int] = field(default_factory=list)
    target: list[float] = MISSING
    weight: list[list[float]] = MISSING
    width: float = MISSING


@dataclass
class SuccessConfig:
    """Success: the reward-space distance stays within ``threshold`` for the last ``last_steps``."""

    threshold: float = MISSING
    last_steps: int = MISSING


@dataclass
class TaskConfig:
    """A task: the gymnasium env (``env.id`` plus constructor kwargs) and what the learner needs."""

    name: str = MISSING
    family: Optional[str] = None  # noqa: UP045  (transfer stays within a family; null: the env id)
    env: dict[str, Any] = MISSING
    horizon: int = MISSING
    angle_dims: list[int] = field(default_factory=list)
    start: StartConfig = field(default_factory=StartConfig)
    reward: Optional[RewardConfig] = None  # noqa: UP045
    policy_size: int = 50
    success: SuccessConfig = field(default_factory=SuccessConfig)


@dataclass
class ModelConfig:
    """Evidence maximisation of the dynamics GP."""

    restarts: int = 3
    max_iter: int = 100
    sparse_above: Optional[int] = 1000  # noqa: UP045  (more tuples than this: the sparse GP; null: never)
    inducing: int = 300


@dataclass
class TransferConfig:
    """Transfer from a source run (Algorithm 1): what is transferred and the compliance gate."""

    source: Optional[str] = None  # noqa: UP045
    hyperparameters: bool = True
    policy: bool = False
    min_compliance: Optional[float] = None  # noqa: UP045
    compliance_temperature: Optional[float] = None  # noqa: UP045
    compliance_resolution: float = 0.0


@dataclass
class SweepConfig:
    """Where an experiment preset (``configs/experiment/``) puts its source and target runs."""

    name: Optional[str] = None  # noqa: UP045
    root: str = "runs/experiments"


@dataclass
class TrainConfig:
    """Top level of ``qtl-train``."""

    task: TaskConfig = MISSING
    propagation: Any = MISSING
    policy: Any = MISSING
    optimizer: Any = MISSING
    rule: Any = field(default_factory=lambda: {"_target_": "qtl.transfer.NoTransfer"})
    seed: int = 0
    random_episodes: int = 1
    episodes: int = 9
    device: str = "cpu"
    threads: Optional[int] = None  # noqa: UP045
    dtype: str = "float64"
    resume: Optional[str] = None  # noqa: UP045
    progress: bool = True
    figure_every: int = 3
    model: ModelConfig = field(default_factory=ModelConfig)
    transfer: TransferConfig = field(default_factory=TransferConfig)
    sweep: SweepConfig = field(default_factory=SweepConfig)


def register_configs() -> None:
    """Register the schema with Hydra's ConfigStore (``defaults: [train_schema, ...]``)."""
    ConfigStore.instance().store(name="train_schema", node=TrainConfig)
