"""A source task's run directory as transfer reads it: θ_s, ψ_s and its data, checked against a target."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from omegaconf import OmegaConf
from torch import Tensor

from qtl.checkpoint import CHECKPOINT_DIR, run_checkpoint
from qtl.data import TransitionDataset, gp_training_pairs
from qtl.errors import CheckpointError, TaskError, TransferError
from qtl.features import AngleFeatures
from qtl.models import DynamicsGP, GPHyperparameters
from qtl.propagation.integration import modelled_outputs
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
    outputs: tuple[int, ...] = ()  # the state dimensions its run modelled, by its propagation.integration
    integration: str = "delta"  # its propagation.integration
    theta_outputs: tuple[int, ...] = ()  # the state dimensions of θ_s's rows: its GP's (constant Δ ones left out)

    def __post_init__(self) -> None:
        # Made by hand without them: every state dimension modelled, θ_s of every modelled output.
        if not self.outputs:
            object.__setattr__(self, "outputs", tuple(range(self.task.state_dim)))
        if not self.theta_outputs:
            object.__setattr__(self, "theta_outputs", self.outputs)

    @classmethod
    def load(cls, path: str | os.PathLike) -> SourceRun:
        """Read a source run directory (its last checkpoint); a clear error when it cannot serve as a source.

        Its task is read from the configuration as the run stored it: the migration of old configs
        (:func:`qtl.runs.read_run`) sits in the config's layer, above transfer, and touches only the group nodes.
        Its modelled outputs follow from its ``propagation.integration``; a θ stored for all D outputs (a run made
        before models held their outputs) is cut to them.
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
            integration = str(OmegaConf.select(cfg, "propagation.integration", default="delta") or "delta")
            outputs = modelled_outputs(integration, task.state_dim, task.kinematics)
        except (KeyError, TypeError, ValueError, TaskError) as err:
            raise TransferError(f"source run {str(path)!r}: its checkpoint cannot be read as a qtl run: {err}") from err
        if theta is None:
            raise TransferError(
                f"source run {str(path)!r} has no learned hyper-parameters yet (its checkpoint after episode "
                f"{checkpoint['episode']} precedes any model): let it learn at least one episode"
            )
        theta, theta_outputs = _theta_of_outputs(checkpoint, theta, task.state_dim, outputs)
        if theta_outputs is None:
            raise TransferError(f"source run {str(path)!r}: its θ has {theta.num_outputs} outputs, its "
                                f"propagation.integration={integration} models {len(outputs)} ({list(outputs)})")
        return cls(path=path, episode=int(checkpoint["episode"]), task=task, theta=theta.detach(), policy=policy,
                   dataset=dataset, outputs=outputs, integration=integration, theta_outputs=theta_outputs)

    def check_compatible(self, target: Task, outputs: Sequence[int] | None = None) -> None:
        """Same task family, state, action and GP input dimensions, and modelled ``outputs``, as the target.

        ``outputs``: the state dimensions the target's GP models (default: all). Else an error naming both.
        """
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
        outputs = tuple(range(target.state_dim)) if outputs is None else tuple(int(d) for d in outputs)
        if outputs != self.outputs:
            raise TransferError(
                f"source run {str(self.path)!r} models outputs {list(self.outputs)} (integration="
                f"{self.integration}), this run models {list(outputs)}: set propagation.integration="
                f"{self.integration} (and the source's task.kinematics), or choose a source of this run's integration"
            )
        if (self.theta.input_dim != target.gp_input_dim or self.theta.num_outputs != len(self.theta_outputs)
                or not set(self.theta_outputs) <= set(outputs)):
            raise TransferError(
                f"source θ_s has E={self.theta.num_outputs} outputs and D={self.theta.input_dim} inputs; "
                f"the target's GP has E={len(outputs)} and D={target.gp_input_dim}"
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
        """The source GP on ``device``: its data of θ_s's outputs with θ_s (no fitting), e.g. for Eq. 14.

        Modelled outputs θ_s lacks (its last fit found their Δ constant) are deterministic, at their mean Δ.
        """
        inputs, targets = gp_training_pairs(self.dataset, features, dtype, device)
        constant = [d for d in self.outputs if d not in self.theta_outputs]
        return DynamicsGP(inputs, targets[:, list(self.theta_outputs)], hyperparameters=self.theta.to(dtype=dtype),
                          outputs=self.theta_outputs, state_dim=self.task.state_dim, constant_outputs=constant,
                          constant_delta=targets[:, constant].mean(dim=0), dtype=dtype)


def _theta_of_outputs(
    checkpoint: dict, theta: GPHyperparameters, state_dim: int, outputs: tuple[int, ...]
) -> tuple[GPHyperparameters, tuple[int, ...] | None]:
    """θ_s and the state dimensions of its rows, among the modelled ``outputs`` (None: θ fits none of them).

    Rows of every modelled output; of the last fit's GP outputs (fewer where its data showed a constant Δ, recorded
    in the checkpoint's ``previous_fit``); or of all D (stored before models held their outputs: cut, exactly).
    """
    if theta.num_outputs == len(outputs):
        return theta, outputs
    previous = checkpoint.get("previous_fit") or {}
    fitted = previous.get("outputs")
    if fitted is not None and len(fitted) == theta.num_outputs and set(fitted) <= set(outputs):
        return theta, tuple(int(d) for d in fitted)
    if theta.num_outputs == state_dim:
        return theta.select(torch.tensor(outputs)), outputs
    return theta, None


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


def source_dirs(source: str | os.PathLike | Sequence[str | os.PathLike]) -> list[Path]:
    """The run directories ``transfer.source`` names: a list of them, one run, or a directory whose subfolders are runs.

    A directory with its own checkpoints is one run; one without them but with subfolders that have some is a library
    of runs (those subfolders, by name); anything else is returned as it is, for :meth:`SourceRun.load` to refuse.
    """
    if isinstance(source, str | os.PathLike):
        path = Path(source).expanduser().resolve()
        if not (path / CHECKPOINT_DIR).is_dir() and path.is_dir():
            runs = sorted(p for p in path.iterdir() if (p / CHECKPOINT_DIR).is_dir())
            if runs:
                return runs
        return [path]
    return [Path(p).expanduser().resolve() for p in source]
