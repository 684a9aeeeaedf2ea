"""Old stored run configs read as today's: each group node typed by its option's schema, old defaults kept.

A checkpoint's config is the config its run was made with; keys added since then read with the value the run
had before they existed (``LEGACY_*``), so that a resumed or transferred run computes as it did.
"""

from __future__ import annotations

from typing import Any

from omegaconf import DictConfig, OmegaConf

from qtl.config.groups import GROUP_SCHEMAS, SCHEMA_BY_TARGET, AutoModelConfig, NoTransferConfig, SparseModelConfig

# A group node stored before its group existed (no `_target_`) is read as this option: `model` (restarts,
# max_iter, sparse_above, inducing) was today's `model=auto`.
LEGACY_TARGETS = {"model": AutoModelConfig._target_}
# Keys whose default changed when the fast paths became the defaults (issue 18): a stored config made
# before the key existed ran with the old value, and reads so (a fresh config always holds the key).
LEGACY_DEFAULTS = {
    "model": {"warm_start": False},
    "optimizer": {"batched": False},
    "kernels": {"backend": "torch", "moments": "reference"},
}
# The same for one option's keys: the sparse GP's K_mm had no jitter before `model.inducing_jitter` existed.
LEGACY_OPTION_DEFAULTS: dict[str, dict[str, Any]] = {
    SparseModelConfig._target_: {"inducing_jitter": 0.0},
    AutoModelConfig._target_: {"inducing_jitter": 0.0},
}
# The environments' package was the top-level `envs` until 1.1: a stored ``module:EnvId`` id of one of them reads
# as today's module (e.g. ``envs.pendulum_hanging:PendulumHanging-v1``).
LEGACY_ENV_MODULE, ENV_MODULE = "envs.", "qtl.envs."

def typed_groups(cfg: DictConfig) -> DictConfig:
    """``cfg`` with each group node merged onto the schema of its option (by ``_target_``): defaults filled, checked.

    A stored run config (a checkpoint's) then compares and merges like a freshly composed one.
    """
    env = cfg.get("task", {}).get("env")
    if env is not None and str(env.get("id", "")).startswith(LEGACY_ENV_MODULE):
        env.id = ENV_MODULE + env.id[len(LEGACY_ENV_MODULE):]
    if cfg.get("rule") is None:  # runs made before transfer existed are PILCO runs
        cfg.rule = OmegaConf.structured(NoTransferConfig)
    for group, old in LEGACY_DEFAULTS.items():
        node = cfg.get(group)
        if node is None and group == "kernels":
            cfg.kernels = {}
            node = cfg.kernels
        if node is not None:
            for key, value in old.items():
                if key not in node:
                    node[key] = value
    for group in GROUP_SCHEMAS:
        node = cfg.get(group)
        target = None if node is None else node.get("_target_", LEGACY_TARGETS.get(group))
        schema = SCHEMA_BY_TARGET.get(target)
        if schema is not None:
            for key, value in LEGACY_OPTION_DEFAULTS.get(target, {}).items():
                if key not in node:
                    node[key] = value
            cfg[group] = OmegaConf.merge(OmegaConf.structured(schema), node)
    return cfg
