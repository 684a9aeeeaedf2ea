"""A run directory read back: its stored configuration migrated to today's schema, its checkpoint, its built parts.

Resume, evaluation, the benchmarks and the probes read a run through here; transfer, below the config's
layer, reads its source's checkpoint through :func:`qtl.checkpoint.run_checkpoint` and its task as stored.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from qtl.build import Parts, build
from qtl.checkpoint import run_checkpoint
from qtl.config import GROUP_SCHEMAS, TrainConfig, typed_groups
from qtl.data import TransitionDataset
from qtl.errors import UserError
from qtl.policies import SquashedPolicy


@dataclass(frozen=True)
class LoadedRun:
    """A run directory as :func:`load_run` reads it: the migrated config (overrides applied), checkpoint, parts."""

    path: Path
    config: DictConfig
    checkpoint: dict[str, Any]
    parts: Parts

    @property
    def episode(self) -> int:
        """The episode the checkpoint was written after."""
        return int(self.checkpoint["episode"])

    def policy(self) -> SquashedPolicy:
        """The run's policy π_ψ with the checkpoint's ψ (the policy that ran :attr:`episode`)."""
        policy = self.parts.initial_policy()
        policy.load_state_dict(self.checkpoint["policy"])
        return policy

    def dataset(self) -> TransitionDataset:
        """The transitions the checkpoint holds (all the run's episodes up to :attr:`episode`)."""
        return TransitionDataset.from_state(self.checkpoint["dataset"], self.parts.task.angle_dims)


def stored_config(checkpoint: dict) -> DictConfig:
    """A checkpoint's run configuration, checked against (and completed by) the schema; old keys migrated."""
    stored = typed_groups(OmegaConf.create(checkpoint["config"]))
    return OmegaConf.merge(OmegaConf.structured(TrainConfig), stored)


def read_run(run_dir: str | os.PathLike, checkpoint: str | os.PathLike | None = None) -> tuple[DictConfig, dict]:
    """A run directory's migrated configuration and newest checkpoint (or ``checkpoint``); one-line error if no run."""
    state = run_checkpoint(run_dir, checkpoint)
    return stored_config(state), state


def with_overrides(cfg: DictConfig, overrides: Sequence[str]) -> DictConfig:
    """``cfg`` with ``group=option`` (any config group's schema) and then ``key=value`` overrides.

    A leading ``+`` is dropped (the typed groups hold every key); a key outside the config is refused, not ignored.
    """
    rest = []
    for override in overrides:
        override = override.removeprefix("+")  # Hydra's "add a key": the typed groups take it as a plain key
        key, _, value = override.partition("=")
        if key.split(".", 1)[0] not in cfg:
            raise UserError(f"unknown override {override!r}: {key.split('.', 1)[0]!r} is not in the run's config")
        if key in GROUP_SCHEMAS:  # `group=option` replaces the whole node, as on the CLI
            if value not in GROUP_SCHEMAS[key]:
                raise UserError(f"unknown {key}={value!r}: choose one of {sorted(GROUP_SCHEMAS[key])}")
            cfg[key] = OmegaConf.structured(GROUP_SCHEMAS[key][value])
        else:
            rest.append(override)
    return OmegaConf.merge(cfg, OmegaConf.from_dotlist(rest))


def load_run(
    run_dir: str | os.PathLike, *, checkpoint: str | os.PathLike | None = None, overrides: Sequence[str] = ()
) -> LoadedRun:
    """A run directory read back: :func:`read_run`'s config with ``overrides`` (:func:`with_overrides`), built."""
    cfg, state = read_run(run_dir, checkpoint)
    cfg = with_overrides(cfg, overrides)
    return LoadedRun(path=Path(run_dir), config=cfg, checkpoint=state, parts=build(cfg))
