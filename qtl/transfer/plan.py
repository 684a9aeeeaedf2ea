"""What a run transfers and how θ evolves: the two seams of Algorithm 1 (ψ at line 1, θ at lines 2 and 13)."""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import nn

from qtl.errors import TransferError
from qtl.features import AngleFeatures
from qtl.models import DynamicsGP, GPHyperparameters
from qtl.task import Task
from qtl.transfer.compliance import DEFAULT_COMPLIANCE, compliance_value
from qtl.transfer.rules import HyperparameterRule
from qtl.transfer.source import SourceRun

log = logging.getLogger(__name__)


class TransferPlan:
    """The transfer settings of a run, checked, and the state of its θ across episodes.

    Built from the ``transfer`` config node, checked first by :func:`qtl.config.validate.check_transfer`, and
    the instantiated ``rule``; the source run is loaded here and must match the task (a
    :class:`TransferError` before any episode runs otherwise). Without a source it is PILCO's plan:
    θ_i = θ_p_i, ψ_0 random. ``outputs``: the state dimensions the run's GP models (default: all); θ and the
    source's θ_s are per modelled output, and the source must model the same ones.
    """

    def __init__(
        self,
        cfg: Mapping[str, Any],
        rule: HyperparameterRule,
        task: Task,
        features: AngleFeatures,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str = "cpu",
        outputs: Sequence[int] | None = None,
    ) -> None:
        self.rule = rule
        self.outputs = tuple(range(task.state_dim)) if outputs is None else tuple(int(d) for d in outputs)
        self.state_dim = task.state_dim
        self.transfer_theta = bool(cfg.get("hyperparameters", True))
        self.transfer_policy = bool(cfg.get("policy", False))
        self.min_compliance = cfg.get("min_compliance")
        self.temperature = cfg.get("compliance_temperature")
        self.resolution = float(cfg.get("compliance_resolution") or 0.0)
        self.compliance_name = str(cfg.get("compliance") or DEFAULT_COMPLIANCE)
        self.bandwidth = str(cfg.get("compliance_bandwidth") or "scott")
        source_dir = cfg.get("source")
        if source_dir is None:
            self.source, self.transfer_theta = None, False
        else:
            self.source = SourceRun.load(source_dir)
            self.source.check_compatible(task, self.outputs)
        self.device = torch.device(device)
        self._source_model = None if self.source is None else self.source.model(features, dtype, device)
        self.theta: GPHyperparameters | None = None  # θ_{i−1}: what the previous model used
        self.theta_outputs = self.outputs  # the state dimensions of θ_{i−1}'s rows
        self.fallen_back = False  # the compliance gate switched this run to PILCO
        self._pilco_psi: dict[str, torch.Tensor] = {}  # PILCO's ψ_0, where a gated run's search starts instead of ψ_s

    # -- line 1: ψ ----------------------------------------------------------------------------

    def initial_policy(self, policy: nn.Module) -> None:
        """ψ_0 = ψ_s when the policy is transferred (Algorithm 1, line 1); else PILCO's ψ_0 (kept for the gate)."""
        if self.transfer_policy and self.source is not None:
            self.source.check_policy(policy)
            self._pilco_psi = {k: v.detach().clone() for k, v in policy.state_dict().items()}
            policy.load_state_dict(self.source.policy)

    # -- lines 2, 12, 13: θ -----------------------------------------------------------------

    def fit_start(self) -> GPHyperparameters | None:
        """Where evidence maximisation starts: θ_s for the free rule (of every modelled output), else the heuristic."""
        if self.rule.warm_start and self.source is not None and not self.fallen_back:
            if self.source.theta_outputs == self.outputs:
                return self.source.theta
            log.info("θ_s holds outputs %s of the modelled %s (the source modelled the others as deterministic): the "
                     "fit starts from the heuristic", list(self.source.theta_outputs), list(self.outputs))
        return None

    def compliance(self, target: DynamicsGP) -> float:
        """Task compliance Λ (Eq. 14) of the target model's tuples; NaN without a source."""
        if self._source_model is None:
            return math.nan
        return compliance_value(self.compliance_name, self._source_model, target, bandwidth=self.bandwidth,
                                temperature=self.temperature, resolution=self.resolution)

    def update(
        self, learned: GPHyperparameters, num_tuples: int, compliance: float = math.nan,
        policy: nn.Module | None = None, outputs: Sequence[int] | None = None,
    ) -> GPHyperparameters:
        """θ of the next model: θ_0 = θ_s (line 2, Eq. 6), then the rule on θ_p (line 13); PILCO: θ_p.

        ``outputs``: the state dimensions of θ_p's rows, the model's GP outputs (default: every modelled output; fewer
        where the data showed some Δ constant, :mod:`qtl.models.constant`). θ_s and θ_{i−1} are matched to them by
        state dimension; an output either lacks (modelled as deterministic there) starts from its θ_p.

        At the first model, Λ (``compliance``, Eq. 14) below ``transfer.min_compliance`` switches the run to
        PILCO for good: θ = θ_p from then on, and a transferred ψ_s in ``policy`` is replaced by PILCO's ψ_0
        (the policy search starts where PILCO's would).
        """
        # The gate reads Λ once, at the first model: its tuples are the initial episodes' (random actions, or
        # ψ_s's when transferred); later tuples follow the run's own policies, whose states move Λ either way.
        if (self.theta is None and self.source is not None and self.min_compliance is not None
                and not self.fallen_back and compliance < float(self.min_compliance)):
            dropped = " and ".join(w for w, on in (("θ_s", self.transfer_theta), ("ψ_s", self.transfer_policy)) if on)
            log.warning("task compliance %.3f < transfer.min_compliance=%s at the first model: %s dropped, the "
                        "run continues as PILCO", compliance, self.min_compliance, dropped or "nothing")
            self.fallen_back = True
            if self.transfer_policy and policy is not None:
                if not self._pilco_psi:
                    raise TransferError("the gate cannot restore PILCO's ψ_0: call initial_policy(policy) first")
                policy.load_state_dict(self._pilco_psi)
        outputs = self.outputs if outputs is None else tuple(int(d) for d in outputs)
        if not self.transfer_theta or self.fallen_back:
            self.theta, self.theta_outputs = learned, outputs
            return learned
        if self.theta is None:
            theta_s = self.source.theta.to(dtype=learned.lengthscales.dtype, device=self.device)
            self.theta = self.rule.start(_aligned(theta_s, self.source.theta_outputs, learned, outputs))
        else:
            self.theta = self.rule.update(_aligned(self.theta, self.theta_outputs, learned, outputs), learned,
                                          num_tuples)
        self.theta_outputs = outputs
        return self.theta

    # -- checkpoints ----------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """θ_{i−1}, the rule's state and the gate's, for a checkpoint."""
        return {
            "theta": None if self.theta is None else self.theta.state_dict(),
            "theta_outputs": list(self.theta_outputs),
            "rule": self.rule.state_dict(),
            "fallen_back": self.fallen_back,
        }

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.theta = None if state["theta"] is None else self._modelled(GPHyperparameters(**state["theta"]))
        self.theta_outputs = tuple(int(d) for d in state.get("theta_outputs", self.outputs))
        self.rule.load_state_dict(state["rule"])
        self.fallen_back = bool(state["fallen_back"])

    def _modelled(self, theta: GPHyperparameters) -> GPHyperparameters:
        """``theta`` on the plan's device, cut to the modelled outputs if it holds all D (stored before issue 63)."""
        if theta.num_outputs == self.state_dim != len(self.outputs):
            theta = theta.select(torch.tensor(self.outputs))
        return theta.to(device=self.device)

    def describe(self) -> str:
        """What is transferred from where, one line."""
        if self.source is None:
            return "no transfer (PILCO)"
        what = [w for w, on in (("θ_s", self.transfer_theta), ("ψ_s", self.transfer_policy)) if on] or ["nothing"]
        return (f"transfer of {' and '.join(what)} from {self.source.path} (episode {self.source.episode}, "
                f"task {self.source.task.name}); rule {self.rule.describe()}")


def _aligned(
    theta: GPHyperparameters, theta_outputs: Sequence[int], learned: GPHyperparameters, outputs: Sequence[int]
) -> GPHyperparameters:
    """θ `E x (D + 2)` of the state dimensions ``outputs``: ``theta``'s row of each it holds, else ``learned``'s.

    ``theta`` holds rows of ``theta_outputs``, ``learned`` rows of ``outputs``; matched as they are when equal.
    """
    held = tuple(int(d) for d in theta_outputs)
    if held == tuple(outputs):
        return theta
    natural = learned.natural().clone()
    for row, d in enumerate(outputs):
        if d in held:
            natural[row] = theta.natural()[held.index(d)].to(natural)
    return GPHyperparameters.from_natural(natural)
