"""``qtl-train``'s configuration: its schema, the migration of old runs' configs, the value checks and ``--help``.

- :mod:`qtl.config.schema`: the dataclasses (a typo or a wrong type fails at compose time), each key's description
  beside its field; :mod:`qtl.config.groups`: one schema per option of the ``propagation``, ``policy``,
  ``optimizer``, ``rule`` and ``model`` groups (``<group>/<option>_schema`` in the ConfigStore).
- :mod:`qtl.config.migrate`: a stored run config read as today's (:func:`typed_groups`).
- :mod:`qtl.config.validate`: every check Hydra cannot make, each a one-line :class:`~qtl.errors.UserError`.
- :mod:`qtl.config.help`: ``qtl-train --help`` and the configuration reference (``python -m qtl.config --markdown``).
- :mod:`qtl.config.cli`: what ``qtl-train`` registers (:func:`register_configs`) and resolves.
"""

from __future__ import annotations

from qtl.config.cli import RUN_DIR_RESOLVER, register_configs, run_dir, show_progress
from qtl.config.groups import (
    GROUP_SCHEMAS,
    SCHEMA_BY_TARGET,
    AdamConfig,
    AutoModelConfig,
    BayesianConfig,
    ExactModelConfig,
    ForgettingConfig,
    FreeConfig,
    LBFGSConfig,
    LinearPolicyConfig,
    MomentMatchingConfig,
    NoTransferConfig,
    ParticlesConfig,
    PlateauConfig,
    RBFNetworkPolicyConfig,
    RBFPolicyConfig,
    SparseModelConfig,
)
from qtl.config.help import (
    HELP_TEMPLATE,
    REFERENCE_COMMAND,
    REFERENCE_PAGE,
    config_groups,
    default_options,
    groups_text,
    help_text,
    reference_markdown,
)
from qtl.config.migrate import LEGACY_DEFAULTS, LEGACY_OPTION_DEFAULTS, LEGACY_TARGETS, typed_groups
from qtl.config.schema import (
    KernelsConfig,
    KinematicsConfig,
    ModelConfig,
    OptimizerConfig,
    PolicyConfig,
    PropagationConfig,
    RewardConfig,
    RuleConfig,
    SearchRewardConfig,
    StartConfig,
    SuccessConfig,
    SweepConfig,
    TaskConfig,
    TrainConfig,
    TransferConfig,
    doc,
)
from qtl.config.validate import check_budget, check_dropout, check_group_keys, check_lr_scales, checked_task

__all__ = [
    "GROUP_SCHEMAS", "HELP_TEMPLATE", "LEGACY_DEFAULTS", "LEGACY_OPTION_DEFAULTS", "LEGACY_TARGETS",
    "REFERENCE_COMMAND", "REFERENCE_PAGE", "RUN_DIR_RESOLVER", "SCHEMA_BY_TARGET", "AdamConfig", "AutoModelConfig",
    "BayesianConfig", "ExactModelConfig", "ForgettingConfig", "FreeConfig", "KernelsConfig", "KinematicsConfig",
    "LBFGSConfig", "LinearPolicyConfig", "ModelConfig", "MomentMatchingConfig", "NoTransferConfig",
    "OptimizerConfig", "ParticlesConfig", "PlateauConfig", "PolicyConfig", "PropagationConfig",
    "RBFNetworkPolicyConfig", "RBFPolicyConfig", "RewardConfig", "RuleConfig", "SearchRewardConfig",
    "SparseModelConfig", "StartConfig", "SuccessConfig", "SweepConfig", "TaskConfig", "TrainConfig",
    "TransferConfig", "check_budget", "check_dropout", "check_group_keys", "check_lr_scales", "checked_task",
    "config_groups", "default_options", "doc", "groups_text", "help_text", "reference_markdown", "register_configs",
    "run_dir", "show_progress", "typed_groups",
]
