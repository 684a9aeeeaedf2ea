"""The full-scale presets' stages as the scale benchmarks measure them: the composed stage, the model it fits."""

from __future__ import annotations

import time
from typing import Any

import torch
from hydra import compose, initialize_config_module
from omegaconf import DictConfig

from qtl.bench.search import collect
from qtl.build import Parts, build
from qtl.config import register_configs
from qtl.models import DynamicsGP, SparseDynamicsGP


def compose_stage(preset: str, overrides: list[str]) -> DictConfig:
    """The composed config of one experiment stage, with its ``hydra`` node (the sweeper's values)."""
    register_configs()
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        return compose(config_name="train", overrides=[f"experiment={preset}", *overrides],
                       return_hydra_config=True)


def stage_model(cfg: DictConfig, seed: int) -> tuple[Parts, DynamicsGP | SparseDynamicsGP, int, float]:
    """A stage's parts and the model it fits on the task's own transitions just past ``model.sparse_above``: n, fit (s).

    (Without a threshold: the whole run's tuples, on the exact GP.)
    """
    parts = build(cfg)
    task = parts.task
    threshold = cfg.model.get("sparse_above")
    n = int(threshold) + task.horizon if threshold is not None else (int(cfg.episodes) + 1) * task.horizon
    data = collect(task, int(cfg.task.policy_size), n, seed)
    tic = time.perf_counter()
    model = parts.fit_dynamics(data, torch.Generator().manual_seed(seed))
    return parts, model, len(data), time.perf_counter() - tic


def model_facts(model: DynamicsGP | SparseDynamicsGP) -> dict[str, Any]:
    """Which model a stage fitted: ``model`` ('exact' or 'sparse') and ``inducing`` (m, or None)."""
    sparse = isinstance(model, SparseDynamicsGP)
    return {"model": "sparse" if sparse else "exact",
            "inducing": int(model.inducing_points.shape[0]) if sparse else None}
