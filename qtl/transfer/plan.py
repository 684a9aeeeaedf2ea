"""What a run transfers and how θ evolves: the two seams of Algorithm 1 (ψ at line 1, θ at lines 2 and 13)."""

from __future__ import annotations

import copy
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from torch import nn

from qtl.errors import TransferError
from qtl.features import AngleFeatures
from qtl.models import DynamicsGP, GPHyperparameters
from qtl.task import Task
from qtl.transfer.compliance import DEFAULT_COMPLIANCE, compliance_value
from qtl.transfer.rules import HyperparameterRule
from qtl.transfer.samples import (
    EFFECTIVE_SAMPLES,
    RELEVANCE,
    SAMPLE_COLUMNS,
    SOURCE_SAMPLES,
    SourceSamples,
    WeightedSamples,
)
from qtl.transfer.source import SourceRun, source_dirs

log = logging.getLogger(__name__)

# transfer.select with several sources: θ_s (and ψ_s) of the most compliant source, or θ_s the Λ-weighted mean of
# the sources' log θ_s (ψ_s still the most compliant one's).
SELECT_MODES = ("compliance", "mixture")
SOURCE_COMPLIANCE_PREFIX = "compliance"  # metrics.csv: Λ_k of source k (Eq. 14), runs with several sources only
SELECTED_SOURCE = "selected_source"  # metrics.csv: k of the source θ_s and ψ_s are taken from (several sources)
SAMPLE_STATE = ("inputs", "targets", "weights", "judged_noise")  # a checkpoint's record of the last source samples


class TransferPlan:
    """The transfer settings of a run, checked, and the state of its θ across episodes.

    Built from the ``transfer`` config node, checked first by :func:`qtl.config.validate.check_transfer`, and
    the instantiated ``rule``; the source runs are loaded here and must match the task (a
    :class:`TransferError` before any episode runs otherwise). Without a source it is PILCO's plan:
    θ_i = θ_p_i, ψ_0 random. ``outputs``: the state dimensions the run's GP models (default: all); θ and the
    source's θ_s are per modelled output, and the source must model the same ones.

    With several sources (``transfer.source`` a list, or a directory of runs) the initial episodes act randomly
    (or by ``transfer.initial_policy``'s ψ_s); at the first model Λ_k (Eq. 14) of every source k chooses
    ``source``, by ``transfer.select``; from then on the plan is the single-source one with that source's ψ_s and
    θ_s (or the mixture's θ_s). Λ_k is computed at every model.

    ``transfer.samples=relevance``: up to ``transfer.max_source_samples`` tuples of the source (the chosen one, from
    the first model after the choice) join each model's data with noise σ_ε²/w, w their relevance under the target's
    tuples at the previous model's θ (θ_s at the first) (:mod:`qtl.transfer.samples`); none once the compliance gate
    has dropped the transfer.
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
        self.select = str(cfg.get("select") or "compliance")
        self.samples = str(cfg.get("samples") or "none")
        self.max_source_samples = int(cfg.get("max_source_samples") or 1)
        self._features, self._dtype = features, dtype
        source = cfg.get("source")
        dirs = [] if source is None else source_dirs(source if isinstance(source, str) else list(source))
        initial = cfg.get("initial_policy")
        initial_dir = None if initial is None else source_dirs(str(initial))[0]
        if initial_dir is not None and initial_dir not in dirs:
            raise TransferError(f"transfer.initial_policy={str(initial_dir)!r} is not one of the sources "
                                f"{[str(d) for d in dirs]}")
        self.sources = [SourceRun.load(d) for d in dirs]  # every source checked before any work
        for run in self.sources:
            run.check_compatible(task, self.outputs)
        if self.select == "mixture" and len({run.theta_outputs for run in self.sources}) > 1:
            held = [list(run.theta_outputs) for run in self.sources]
            raise TransferError("transfer.select=mixture averages θ_s over the sources: theirs hold different outputs "
                                f"({held}); use transfer.select=compliance")
        # The source θ_s and ψ_s come from: the only one, or (several) the one chosen at the first model.
        self.source = self.sources[0] if len(self.sources) == 1 else None
        self.transfer_theta = self.transfer_theta and bool(self.sources)
        self.theta_s = None if self.source is None else self.source.theta  # θ_s: the source's, or the mixture's
        self.theta_s_outputs = self.outputs if self.source is None else self.source.theta_outputs
        # The source whose ψ_s acts in the initial episodes: initial_policy's, or the only source's under policy=true.
        self.initial_source = (self.sources[dirs.index(initial_dir)] if initial_dir is not None
                               else self.source if self.transfer_policy else None)
        self.compliances: list[float] = []  # Λ_k of every source at the last model (several sources)
        self.selected: int | None = 0 if self.source is not None else None  # k of the source chosen
        self._chosen_compliances: list[float] = []  # Λ_k the choice was made by (several sources)
        self.device = torch.device(device)
        self._source_models = [run.model(features, dtype, device) for run in self.sources]
        self.theta: GPHyperparameters | None = None  # θ_{i−1}: what the previous model used
        self.theta_outputs = self.outputs  # the state dimensions of θ_{i−1}'s rows
        self.fallen_back = False  # the compliance gate switched this run to PILCO
        self._pilco_psi: dict[str, torch.Tensor] = {}  # PILCO's ψ_0, where a gated run's search starts instead of ψ_s
        self.weighted: WeightedSamples | None = None  # the source tuples of the last model, with their relevance
        self.judged: GPHyperparameters | None = None  # θ of the target's own tuples that judged them ...
        self.judged_outputs: tuple[int, ...] = ()  # ... and the outputs it has rows for
        self._tuples: dict[int, SourceSamples] = {}  # source k's tuples as GP training pairs (transfer.samples)

    # -- line 1: ψ ----------------------------------------------------------------------------

    @property
    def several(self) -> bool:
        """Whether the run has several sources, one to be chosen at the first model."""
        return len(self.sources) > 1

    def initial_policy(self, policy: nn.Module) -> None:
        """ψ_0 = ψ_s when the policy is transferred (Algorithm 1, line 1); else PILCO's ψ_0 (kept for the gate).

        With several sources ψ_0 stays PILCO's until the first model chooses one; every ψ_s is checked now.
        """
        acting = self.sources if self.transfer_policy else [r for r in (self.initial_source,) if r is not None]
        for run in acting:
            run.check_policy(policy)
        if self.transfer_policy and self.sources:
            self._pilco_psi = {k: v.detach().clone() for k, v in policy.state_dict().items()}
            if self.source is not None:
                policy.load_state_dict(self.source.policy)

    def initial_actor(self, policy: nn.Module) -> nn.Module | None:
        """What acts in the initial episodes (line 3): ``policy`` holding ψ_s, a source's ψ_s, or None (random)."""
        if self.initial_source is None:
            return None
        if self.initial_source is self.source and self.transfer_policy:
            return policy  # ψ_0 = ψ_s already
        acting = copy.deepcopy(policy)
        acting.load_state_dict(self.initial_source.policy)
        return acting

    # -- lines 2, 12, 13: θ -----------------------------------------------------------------

    def fit_start(self) -> GPHyperparameters | None:
        """Where evidence maximisation starts: θ_s for the free rule (of every modelled output), else the heuristic."""
        if self.rule.warm_start and self.theta_s is not None and not self.fallen_back:
            if self.theta_s_outputs == self.outputs:
                return self.theta_s
            log.info("θ_s holds outputs %s of the modelled %s (the source modelled the others as deterministic): the "
                     "fit starts from the heuristic", list(self.theta_s_outputs), list(self.outputs))
        return None

    def compliance(self, target: DynamicsGP) -> float:
        """Task compliance Λ (Eq. 14) of the target model's tuples; NaN without a source.

        With several sources: Λ_k of each (:attr:`compliances`), the source chosen at the first call
        (:meth:`choose`), and Λ of the chosen one returned.
        """
        if not self.sources:
            return math.nan
        self.compliances = [
            compliance_value(self.compliance_name, model, target, bandwidth=self.bandwidth,
                             temperature=self.temperature, resolution=self.resolution)
            for model in self._source_models]
        if self.selected is None:
            self.choose(self.compliances)
        return self.compliances[self.selected]

    def choose(self, compliances: Sequence[float]) -> int:
        """Choose the source of θ_s and ψ_s by its Λ_k (Eq. 14, `K`): the most compliant (the first of ties); its k.

        ``select=mixture``: θ_s is the Λ-weighted mean of the sources' log θ_s (:func:`mixture_theta`).
        """
        values = [float(c) for c in compliances]
        best = max(range(len(values)), key=lambda k: -math.inf if math.isnan(values[k]) else values[k])
        self.selected, self.source = best, self.sources[best]
        self.theta_s_outputs = self.source.theta_outputs
        if self.select == "mixture":
            self.theta_s = mixture_theta([run.theta for run in self.sources], values)
        else:
            self.theta_s = self.source.theta
        self._chosen_compliances = values
        log.info("task compliance per source %s: %s chosen (select=%s)",
                 ", ".join(f"{k}: {v:.4f}" for k, v in enumerate(values)), self.source.path, self.select)
        return best

    # -- line 12: source samples in the data ------------------------------------------------

    def source_samples(self, judge: Callable[[GPHyperparameters | None], DynamicsGP]) -> WeightedSamples | None:
        """The source's tuples for the next model with their relevance under the target's tuples.

        None unless ``transfer.samples=relevance`` and a source is chosen and not dropped by the gate. Judged at θ of
        the target's own tuples: ``judge(start)`` fits them alone from ``start``, the last judging θ (θ_s before the
        first). Not at the last model's θ, which the source tuples themselves helped fit: they would vouch for
        themselves.
        """
        if self.samples != "relevance" or self.source is None or self.fallen_back:
            return None
        own = judge(self._judging_start())
        self.judged, self.judged_outputs = own.hyperparameters, tuple(own.outputs)
        self.weighted = self._source_tuples().judged_by(own)
        return self.weighted

    def _judging_start(self) -> GPHyperparameters | None:
        """Where the judging fit starts: the last judging θ, else θ_s, of every modelled output; else the heuristic."""
        if self.judged is not None and self.judged_outputs == self.outputs:
            return self.judged
        if self.theta_s is not None and self.theta_s_outputs == self.outputs:
            return self.theta_s
        return None

    def _source_tuples(self) -> SourceSamples:
        """The chosen source's tuples as GP training pairs of the modelled outputs, thinned evenly (made once)."""
        key = self.sources.index(self.source)
        if key not in self._tuples:
            self._tuples[key] = SourceSamples.of(self.source.dataset, self._features, self.outputs,
                                                 self.max_source_samples, self._dtype, self.device)
        return self._tuples[key]

    def sample_columns(self) -> list[str]:
        """The ``metrics.csv`` columns of the source samples: none unless ``transfer.samples=relevance``."""
        return list(SAMPLE_COLUMNS) if self.samples == "relevance" else []

    def sample_row(self) -> dict[str, float]:
        """The source samples of the last model (:meth:`sample_columns`): 0 samples and NaN w when it had none."""
        if self.samples != "relevance":
            return {}
        if self.weighted is None:
            return {SOURCE_SAMPLES: 0.0, RELEVANCE: math.nan, EFFECTIVE_SAMPLES: 0.0}
        return self.weighted.row()

    def compliance_columns(self) -> list[str]:
        """The ``metrics.csv`` columns of Λ_k per source and the chosen k: none with a single source."""
        if not self.several:
            return []
        return [f"{SOURCE_COMPLIANCE_PREFIX}/{k}" for k in range(len(self.sources))] + [SELECTED_SOURCE]

    def compliance_row(self) -> dict[str, float]:
        """Λ_k of the last model and the chosen k as ``{column: value}`` (:meth:`compliance_columns`)."""
        if not self.several or not self.compliances:
            return {}
        row: dict[str, float] = {f"{SOURCE_COMPLIANCE_PREFIX}/{k}": v for k, v in enumerate(self.compliances)}
        row[SELECTED_SOURCE] = self.selected
        return row

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
        if (self.theta is None and self.several and self.transfer_policy and not self.fallen_back
                and policy is not None and self.source is not None):
            policy.load_state_dict(self.source.policy)  # ψ_0 = ψ_s of the source chosen at this first model
        outputs = self.outputs if outputs is None else tuple(int(d) for d in outputs)
        if not self.transfer_theta or self.fallen_back:
            self.theta, self.theta_outputs = learned, outputs
            return learned
        if self.theta is None:
            theta_s = self.theta_s.to(dtype=learned.lengthscales.dtype, device=self.device)
            self.theta = self.rule.start(_aligned(theta_s, self.theta_s_outputs, learned, outputs))
        else:
            self.theta = self.rule.update(_aligned(self.theta, self.theta_outputs, learned, outputs), learned,
                                          num_tuples)
        self.theta_outputs = outputs
        return self.theta

    # -- checkpoints ----------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """θ_{i−1}, the rule's state and the gate's, for a checkpoint."""
        state = {
            "theta": None if self.theta is None else self.theta.state_dict(),
            "theta_outputs": list(self.theta_outputs),
            "rule": self.rule.state_dict(),
            "fallen_back": self.fallen_back,
        }
        if self.several and self.selected is not None:
            state["chosen_by"] = list(self._chosen_compliances)  # Λ_k at the first model: the choice, and its θ_s
        if self.weighted is not None:  # the last model's source tuples and their relevance
            state["samples"] = {key: getattr(self.weighted, key).cpu() for key in SAMPLE_STATE}
            state["judged"] = {"theta": self.judged.state_dict(), "outputs": list(self.judged_outputs)}
        return state

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.theta = None if state["theta"] is None else self._modelled(GPHyperparameters(**state["theta"]))
        self.theta_outputs = tuple(int(d) for d in state.get("theta_outputs", self.outputs))
        self.rule.load_state_dict(state["rule"])
        self.fallen_back = bool(state["fallen_back"])
        if self.several and state.get("chosen_by") is not None:
            self.choose(state["chosen_by"])
        samples = state.get("samples")
        self.weighted = None if samples is None else WeightedSamples(
            *(samples[key].to(dtype=self._dtype, device=self.device) for key in SAMPLE_STATE))
        judged = state.get("judged")
        self.judged = None if judged is None else GPHyperparameters(**judged["theta"]).to(device=self.device)
        self.judged_outputs = () if judged is None else tuple(int(d) for d in judged["outputs"])

    def _modelled(self, theta: GPHyperparameters) -> GPHyperparameters:
        """``theta`` on the plan's device, cut to the modelled outputs if it holds all D (stored before issue 63)."""
        if theta.num_outputs == self.state_dim != len(self.outputs):
            theta = theta.select(torch.tensor(self.outputs))
        return theta.to(device=self.device)

    def describe(self) -> str:
        """What is transferred from where, one line."""
        if not self.sources:
            return "no transfer (PILCO)"
        what = [w for w, on in (("θ_s", self.transfer_theta), ("ψ_s", self.transfer_policy),
                                (f"up to {self.max_source_samples} source tuples weighted by relevance",
                                 self.samples == "relevance")) if on] or ["nothing"]
        if self.several:
            listed = "; ".join(f"{k}: {run.path} (episode {run.episode}, task {run.task.name})"
                               for k, run in enumerate(self.sources))
            acting = "random actions" if self.initial_source is None else f"ψ_s of {self.initial_source.path}"
            return (f"transfer of {' and '.join(what)} from one of {len(self.sources)} sources, chosen by task "
                    f"compliance at the first model (select={self.select}): {listed}; initial episodes: {acting}; "
                    f"rule {self.rule.describe()}")
        return (f"transfer of {' and '.join(what)} from {self.source.path} (episode {self.source.episode}, "
                f"task {self.source.task.name}); rule {self.rule.describe()}")


def mixture_theta(thetas: Sequence[GPHyperparameters], compliances: Sequence[float]) -> GPHyperparameters:
    """θ_s = exp(Σ_k w_k log θ_k), w_k = Λ_k / Σ_j Λ_j (equal where every Λ_k is 0): each θ_k `E x (D + 2)`."""
    logs = torch.stack([theta.log() for theta in thetas])  # K x E x (D + 2)
    weights = torch.tensor([max(float(c), 0.0) if math.isfinite(float(c)) else 0.0 for c in compliances],
                           dtype=logs.dtype)  # K
    total = weights.sum()
    weights = weights / total if total > 0 else torch.full_like(weights, 1.0 / len(thetas))
    return GPHyperparameters.from_natural((weights[:, None, None] * logs).sum(0).exp())


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
