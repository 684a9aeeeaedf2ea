"""A source task's run directory as transfer reads it: θ_s, ψ_s and its data, checked against a target."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import OmegaConf
from torch import Tensor

from qtl.checkpoint import run_checkpoint
from qtl.data import TransitionDataset, gp_training_pairs
from qtl.errors import CheckpointError, TaskError, TransferError
from qtl.features import AngleFeatures
from qtl.models import DynamicsGP, GPHyperparameters
from qtl.task import Task


@dataclass(frozen=True)
class SourceRun:
    """What a finished source run leaves for transfer: its last checkpoint's θ_s, ψ_s, data and task."""

    path: Path
    episode: int  # the episode of the checkpoint read
    task: Task
    theta: GPHyperparameters  # θ_s: the θ of the source's last model
    policy: dict[str, Tensor]  # ψ_s: the source's final policy parameters (a state dict)
    dataset: TransitionDataset

    @classmethod
    def load(cls, path: str | os.PathLike) -> SourceRun:
        """Read a source run directory (its last checkpoint); a clear error when it cannot serve as a source.

        Its task is read from the configuration as the run stored it: the migration of old configs
        (:func:`qtl.runs.read_run`) sits in the config's layer, above transfer, and touches only the group nodes.
        """
        path = Path(path).expanduser().resolve()
        try:
            checkpoint = run_checkpoint(path)
        except CheckpointError as err:
            raise TransferError(f"transfer.source={str(path)!r} is not a usable source run: {err}") from err
        try:
            cfg = OmegaConf.create(checkpoint["config"])
            task = Task.from_config(OmegaConf.to_container(cfg.task, resolve=True))
            dataset = TransitionDataset.from_state(checkpoint["dataset"], task.angle_dims)
            theta = _stored_theta(checkpoint)
            policy = dict(checkpoint["policy"])
        except (KeyError, TypeError, ValueError, TaskError) as err:
            raise TransferError(f"source run {str(path)!r}: its checkpoint cannot be read as a qtl run: {err}") from err
        if theta is None:
            raise TransferError(
                f"source run {str(path)!r} has no learned hyper-parameters yet (its checkpoint after episode "
                f"{checkpoint['episode']} precedes any model): let it learn at least one episode"
            )
        return cls(path=path, episode=int(checkpoint["episode"]), task=task, theta=theta.detach(), policy=policy,
                   dataset=dataset)

    def check_compatible(self, target: Task) -> None:
        """Same task family, state, action and GP input dimensions as the target; else an error naming both."""
        source = self.task
        if source.family != target.family:
            raise TransferError(
                f"source run {str(self.path)!r} is task {source.name!r} of family {source.family!r} "
                f"({source.env_id}); the target task {target.name!r} is of family {target.family!r} "
                f"({target.env_id}): transfer only works within one family"
            )
        sides = {
            "state dimension": (source.state_dim, target.state_dim),
            "action dimension": (source.action_dim, target.action_dim),
            "angle dimensions": (list(source.angle_dims), list(target.angle_dims)),
            "GP input dimension": (source.gp_input_dim, target.gp_input_dim),
        }
        for what, (src, tgt) in sides.items():
            if src != tgt:
                raise TransferError(
                    f"source and target do not match: {what} is {src} in the source run {str(self.path)!r} "
                    f"({source.name}) and {tgt} in the target task ({target.name})"
                )
        if self.theta.input_dim != target.gp_input_dim or self.theta.num_outputs != target.state_dim:
            raise TransferError(
                f"source θ_s has E={self.theta.num_outputs} outputs and D={self.theta.input_dim} inputs; "
                f"the target's GP has E={target.state_dim} and D={target.gp_input_dim}"
            )

    def check_policy(self, policy: torch.nn.Module) -> None:
        """ψ_s fits the target's policy exactly (same parameters and shapes); else an error naming both."""
        target = {k: tuple(v.shape) for k, v in policy.state_dict().items()}
        source = {k: tuple(v.shape) for k, v in self.policy.items()}
        if target != source:
            raise TransferError(
                f"transfer.policy=true: the source policy ({str(self.path)!r}) has parameters {source}, the "
                f"target's policy has {target}; use the same policy config (e.g. task.policy_size) on both"
            )

    def model(
        self, features: AngleFeatures, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu"
    ) -> DynamicsGP:
        """The source GP on ``device``: its own data with θ_s (no fitting), e.g. for task compliance (Eq. 14)."""
        inputs, targets = gp_training_pairs(self.dataset, features, dtype, device)
        return DynamicsGP(inputs, targets, hyperparameters=self.theta.to(dtype=dtype), dtype=dtype)


def _stored_theta(checkpoint: dict) -> GPHyperparameters | None:
    """θ of the checkpoint's latest model; from its last metrics row when the checkpoint predates the "theta" key.

    The metrics rows hold every θ_i in full float64 precision (``theta/out{j}/...`` columns), so
    the two sources agree exactly.
    """
    if "theta" in checkpoint:
        return None if checkpoint["theta"] is None else GPHyperparameters(**checkpoint["theta"])
    learned = [row for row in checkpoint["metrics"] if row.get("kind") == "policy"]
    if not learned:
        return None
    return GPHyperparameters.from_dict(learned[-1], prefix="theta/")  # the θ_i columns (qtl.recorder.THETA_PREFIX)
