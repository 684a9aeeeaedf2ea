"""What Algorithm 1 carries from one episode to the next: the tuples, θ, ψ, the rule's state, the records, the RNG."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torch import nn

from qtl.build import Parts
from qtl.checkpoint import save_checkpoint, set_rng_state
from qtl.data import TransitionDataset
from qtl.models import GPHyperparameters, PreviousFit
from qtl.recorder import Records
from qtl.seeding import derive_seed, torch_generator
from qtl.transfer.plan import TransferPlan


@dataclass
class RunState:
    """A run between two episodes: all a checkpoint holds, and the seed every episode's RNG streams derive from.

    The global RNG streams (Python, numpy, torch) are not held here but live in their modules: :meth:`save`
    writes them to the checkpoint and :meth:`load` restores them.
    """

    seed: int  # the run's seed: the episode's streams are derive_seed(seed, episode, stream) (qtl.seeding)
    data: TransitionDataset  # the tuples so far (lines 3 and 11)
    policy: nn.Module  # π(ψ)
    plan: TransferPlan  # θ_{i−1} of the updating rule, the rule's state and the compliance gate's (line 13)
    theta: GPHyperparameters | None = None  # θ of the latest model (none before the first fit)
    previous: PreviousFit | None = None  # θ_p (and Z) of the latest fit, where model.warm_start starts from
    episodes: int = 0  # episodes done: the next one's index
    resumed_at: int | None = None  # the first episode of a resumed session (None: a fresh run)
    records: Records = field(default_factory=Records)  # metrics.csv's, timings.csv's and health.csv's rows so far

    @classmethod
    def fresh(cls, parts: Parts, plan: TransferPlan) -> RunState:
        """Lines 1-2: π ← π(ψ_s) when ψ_s is transferred (else PILCO's ψ_0); no tuples; θ waits for the first model."""
        policy = parts.initial_policy()
        plan.initial_policy(policy)
        return cls(parts.seed, TransitionDataset(parts.task.state_dim, parts.task.action_dim, parts.task.angle_dims),
                   policy, plan)

    @classmethod
    def load(cls, checkpoint: dict[str, Any], parts: Parts, plan: TransferPlan) -> RunState:
        """The state a checkpoint (:meth:`save`'s, as :func:`qtl.checkpoint.run_checkpoint` reads it) holds.

        The global RNG streams are restored to the checkpoint's. Checkpoints made before ``health.csv``, transfer
        or ``model.warm_start`` lack their keys: none recorded, PILCO, no previous fit.
        """
        state = cls.fresh(parts, plan)
        state.data = TransitionDataset.from_state(checkpoint["dataset"], parts.task.angle_dims)
        state.policy.load_state_dict(checkpoint["policy"])
        state.records = Records([dict(r) for r in checkpoint["metrics"]], [dict(t) for t in checkpoint["timings"]],
                                [dict(h) for h in checkpoint.get("health", [])])
        state.theta = None if checkpoint["theta"] is None else GPHyperparameters(**checkpoint["theta"])
        state.previous = PreviousFit.of_checkpoint(checkpoint)
        if "transfer" in checkpoint:
            plan.load_state_dict(checkpoint["transfer"])
        state.episodes = checkpoint["episode"] + 1
        state.resumed_at = state.episodes
        set_rng_state(checkpoint["rng"])
        return state

    def checkpoint(self, cfg: DictConfig) -> dict[str, Any]:
        """What :meth:`save` writes (beside the episode and the global RNG states): the run's config and this state."""
        return {
            "config": OmegaConf.to_yaml(cfg),
            "dataset": self.data.state(),
            "theta": None if self.theta is None else self.theta.state_dict(),
            "previous_fit": None if self.previous is None else self.previous.state_dict(),
            "transfer": self.plan.state_dict(),
            "policy": {k: v.detach().cpu().clone() for k, v in self.policy.state_dict().items()},
            "metrics": self.records.rows,
            "timings": self.records.timings,
            "health": self.records.health,
        }

    def save(self, run_dir: str | os.PathLike, cfg: DictConfig) -> Path:
        """Checkpoint the run after its last episode done, with the global RNG states (:func:`save_checkpoint`)."""
        return save_checkpoint(run_dir, self.episodes - 1, self.checkpoint(cfg))

    def stream(self, stream: int) -> int:
        """The seed of one RNG stream (``qtl.seeding``'s ``*_STREAM``) of the next episode."""
        return derive_seed(self.seed, self.episodes, stream)

    def generator(self, stream: int) -> torch.Generator:
        """A torch generator on one RNG stream of the next episode."""
        return torch_generator(self.seed, self.episodes, stream)
