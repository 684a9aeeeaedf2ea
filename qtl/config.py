"""Dataclass schema of the Hydra configuration: a typo or a wrong type fails at compose time.

Every key carries its description (``metadata["help"]``); ``qtl-train --help`` lists them, and so does the
configuration reference of the docs (``python -m qtl.config --markdown``), from the same walk of the schema.
Each option of the ``propagation``, ``policy``, ``optimizer`` and ``rule`` groups has its own
schema (``<group>/<option>_schema`` in the ConfigStore, named first in the option's defaults list).
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import os
import re
import sys
import typing
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import II, MISSING, DictConfig, OmegaConf

from qtl.errors import UserError
from qtl.models.fitting import (
    DEFAULT_INDUCING,
    DEFAULT_JITTER,
    DEFAULT_MAX_ITER,
    DEFAULT_RESTARTS,
    DEFAULT_SPARSE_ABOVE,
)
from qtl.propagation.particles import DEFAULT_NUM_FEATURES
from qtl.task import DEFAULT_START_MIN_STD

# OmegaConf reads these annotations at run time: keep `Optional[...]` and `List`-style types
# that it understands (PEP 604 unions are not supported by OmegaConf's structured configs).

RUN_DIR_RESOLVER = "qtl.run_dir"
HELP_WIDTH = 44  # column of the descriptions in --help
PERTURBATION_HELP = "std of the restarts' perturbation, relative to each parameter's spread"
BATCHED_HELP = ("all restarts at once: one batched rollout evaluates every running restart, each restart keeps its "
                "own optimiser (L-BFGS: the sequential run, in lockstep) (false: one restart after the other)")
SPACE_HELP = "log | natural: the space θ is handled in"
INDUCING_HELP = "inducing inputs of the sparse GP (PILCO's FITC uses ~300)"
INDUCING_JITTER_HELP = "the sparse GP's jitter on K_mm's diagonal, a fraction of α² (0: none)"


def doc(text: str) -> dict[str, str]:
    """A schema field's metadata: its one-line description, shown by ``qtl-train --help``."""
    return {"help": text}


# -- task --------------------------------------------------------------------------------------


@dataclass
class StartConfig:
    """Start distribution N(mean, diag(std²)); null reads the env's ``start_mean``/``start_std``.

    With neither here nor on the env, μ_0 and σ_0 are estimated from the episodes' initial states.
    """

    mean: Optional[list[float]] = field(  # noqa: UP045
        default=None, metadata=doc("start mean `D` (null: the env's start_mean)"),
    )
    std: Optional[list[float]] = field(  # noqa: UP045
        default=None, metadata=doc("start std `D` (null: the env's start_std)"),
    )
    min_std: float = field(
        default=DEFAULT_START_MIN_STD,
        metadata=doc("floor on the std of a start distribution estimated from the episodes' initial states"),
    )


@dataclass
class RewardConfig:
    """Saturating reward (Eq. 13) for an env that does not expose ``reward_spec`` itself."""

    angle_dims: list[int] = field(default_factory=list, metadata=doc("state dimensions the reward sees as (sin, cos)"))
    target: list[float] = field(default=MISSING, metadata=doc("target y* in the augmented state"))
    weight: list[list[float]] = field(default=MISSING, metadata=doc("weight matrix W of (y-y*)"))
    width: float = field(default=MISSING, metadata=doc("width of the saturating reward"))


@dataclass
class SearchRewardConfig:
    """An angle/position search cost exp(−½ Σ (δ_d/σ_d)²) on the raw state (particle searches, ``search_cost``)."""

    target: list[Optional[float]] = field(  # noqa: UP045
        default=MISSING, metadata=doc("target x* per raw state dimension (null: left out)"),
    )
    widths: list[Optional[float]] = field(  # noqa: UP045
        default=MISSING, metadata=doc("width σ_d per dimension (null: left out)"),
    )
    angles: str = field(
        default="wrapped",
        metadata=doc("δ on angle dims: wrapped (θ − θ* in [−π, π), every turn free) or absolute (|θ| − θ* on the raw "
                     "angle, MC-PILCO's: every extra turn costs)"),
    )


@dataclass
class KinematicsConfig:
    """Which state dimensions are positions and which their velocities (particles' speed integration)."""

    positions: list[int] = field(default=MISSING, metadata=doc("state indices of the positions q"))
    velocities: list[int] = field(default=MISSING, metadata=doc("state indices of their velocities q̇, in order"))
    period: Optional[float] = field(  # noqa: UP045
        default=None, metadata=doc("control period T in s (null: the env's dt × action_repeat)"),
    )


@dataclass
class SuccessConfig:
    """Success: the reward-space distance stays within ``threshold`` for the last ``last_steps``."""

    threshold: float = field(default=MISSING, metadata=doc("distance to the target that counts as success"))
    last_steps: int = field(
        default=MISSING, metadata=doc("steps at the end of an episode that must all succeed (<= task.horizon)"),
    )


@dataclass
class TaskConfig:
    """A task: the gymnasium env (``env.id`` plus constructor kwargs) and what the learner needs."""

    name: str = field(default=MISSING, metadata=doc("the task's name"))
    family: Optional[str] = field(  # noqa: UP045
        default=None, metadata=doc("transfer stays within a family (null: the env id)"),
    )
    env: dict[str, Any] = field(
        default=MISSING, metadata=doc("env id and the constructor kwargs the task changes (+task.env.<kwarg>=)"),
    )
    horizon: int = field(
        default=MISSING, metadata=doc("steps per episode and prediction horizon (the env's horizon kwarg)"),
    )
    action_repeat: int = field(
        default=1, metadata=doc("env steps each action is held for, rewards summed (task.horizon counts held steps)"),
    )
    angle_dims: list[int] = field(
        default_factory=list, metadata=doc("state dimensions that are angles: (sin, cos) for GP and policy"),
    )
    state_names: Optional[list[str]] = field(  # noqa: UP045
        default=None, metadata=doc("names of the state dimensions (null: the env's)"),
    )
    start: StartConfig = field(
        default_factory=StartConfig, metadata=doc("start distribution x_0 ~ N(mean, diag(std²))"),
    )
    reset_options: Optional[dict[str, Any]] = field(  # noqa: UP045
        default=None, metadata=doc("options passed to env.reset(seed=..., options=...) (null: none)"),
    )
    reward: Optional[RewardConfig] = field(  # noqa: UP045
        default=None, metadata=doc("saturating reward (null: the env's reward_spec)"),
    )
    search_reward: Optional[SearchRewardConfig] = field(  # noqa: UP045
        default=None, metadata=doc("an angle/position cost a particle search may score (propagation.search_cost)"),
    )
    kinematics: Optional[KinematicsConfig] = field(  # noqa: UP045
        default=None, metadata=doc("positions and velocities, for propagation.integration=speed (null: none)"),
    )
    policy_size: int = field(default=50, metadata=doc("RBF basis functions of the policy"))
    success: SuccessConfig = field(default_factory=SuccessConfig, metadata=doc("when an episode counts as a success"))


# -- groups: one schema per option, typed by the group's base ------------------------------------


@dataclass
class PropagationConfig:
    """Base of the ``propagation`` options: a partial propagator, completed with model, policy and reward."""

    _target_: str = MISSING
    _partial_: bool = True


@dataclass
class MomentMatchingConfig(PropagationConfig):
    """Analytic moment matching through policy and GP (PILCO; Eq. 1-5)."""

    _target_: str = "qtl.propagation.MomentMatching"
    include_noise: bool = field(default=False, metadata=doc("add the GP's noise variance to every predicted state"))


@dataclass
class ParticlesConfig(PropagationConfig):
    """P reparameterised samples through policy and GP (MC-PILCO / PIPPS; Eq. 4), common random numbers."""

    _target_: str = "qtl.propagation.Particles"
    include_noise: bool = field(default=True, metadata=doc("add the GP's noise variance to every predicted state"))
    num_particles: int = field(default=400, metadata=doc("particles P"))
    resample_every: int = field(
        default=0, metadata=doc("fresh base noise every k evaluations (0: fixed per search; pair k > 0 with Adam)"),
    )
    expected_reward: bool = field(
        default=True, metadata=doc("score E[r(x_t) | x_{t-1}] per particle (false: r of the drawn state)"),
    )
    gaussian_resampling: bool = field(
        default=False, metadata=doc("redraw the particles from their fitted Gaussian every step (PIPPS)"),
    )
    sampling: str = field(
        default="marginal",
        metadata=doc("marginal | pathwise: a fresh GP draw every step, or one GP function per particle for the "
                     "rollout (Matheron's rule, random Fourier features; O(n + L) per step instead of O(n²))"),
    )
    num_features: int = field(
        default=DEFAULT_NUM_FEATURES, metadata=doc("random Fourier features L per output of a pathwise function"),
    )
    path_dtype: str = field(
        default="float64",
        metadata=doc("float64 | float32: the dtype pathwise functions are evaluated in (float32: ~2× faster, "
                     "round-off ~1e-7, far below the features' Monte Carlo error ~1/√L)"),
    )
    reward_width_scale: float = field(
        default=1.0, metadata=doc("search the task's reward with its width × this (a wider cost, as MC-PILCO's; "
                                  "success is still the task's test; the predicted return is under it)"),
    )
    reward_task_weight: float = field(
        default=0.0, metadata=doc("the task's own reward's share w of the search reward: (1 − w) × widened + w × "
                                  "the task's, wide enough to climb and sharp enough to hold the target"),
    )
    search_cost: str = field(
        default="widened", metadata=doc("widened | task | auto: the search's base reward, the task's widened, or the "
                                        "task's declared search_reward (angle/position cost, as MC-PILCO's), or that "
                                        "when the task declares one"),
    )
    integration: str = field(
        default="delta", metadata=doc("delta | speed: x + Δ in every dimension, or the GP's Δ of the velocities "
                                      "with positions integrated, q + T q̇ + (T/2) Δq̇ (MC-PILCO; task.kinematics)"),
    )
    search_start_scale: float = field(
        default=1.0, metadata=doc("the search's start spread: N(μ_0, s² Σ_0), s in (0, 1] (lower gradient variance "
                                  "on chaotic rollouts; predictions keep the task's start)"),
    )
    seed: int = field(default=II("seed"), metadata=doc("seed of the base noise"))


@dataclass
class PolicyConfig:
    """Base of the ``policy`` options: a partial factory, completed with the dimensions and start features."""

    _target_: str = MISSING
    _partial_: bool = True


@dataclass
class RBFPolicyConfig(PolicyConfig):
    """RBF network (Eq. 5), support points drawn around the start distribution, squashed to the action bounds."""

    _target_: str = "qtl.policies.rbf_policy"
    num_basis: int = field(default=II("task.policy_size"), metadata=doc("basis functions (default task.policy_size)"))


@dataclass
class RBFNetworkPolicyConfig(PolicyConfig):
    """RBF network with free weights (MC-PILCO's sum of Gaussians): centres spread over the states, dropout."""

    _target_: str = "qtl.policies.rbf_network_policy"
    num_basis: int = field(default=II("task.policy_size"), metadata=doc("basis functions (default task.policy_size)"))
    centre_range: float = field(
        default=3.141592653589793,
        metadata=doc("initial centres: non-angle state dims uniform in ± this, angles uniform (MC-PILCO: π)"),
    )
    weight_range: float = field(default=0.5, metadata=doc("initial weights uniform in ± this (before squashing)"))
    lengthscale: float = field(
        default=0.7071067811865476, metadata=doc("initial length-scales (MC-PILCO's 1 in its exp(−d²) form)"),
    )


@dataclass
class LinearPolicyConfig(PolicyConfig):
    """Linear policy u = W y + b, squashed to the action bounds."""

    _target_: str = "qtl.policies.linear_policy"


@dataclass
class OptimizerConfig:
    """Base of the ``optimizer`` options: a policy search with restarts, the best ψ kept."""

    _target_: str = MISSING


@dataclass
class LBFGSConfig(OptimizerConfig):
    """Policy search by L-BFGS."""

    _target_: str = "qtl.policy_search.LBFGSSearch"
    max_iter: int = field(default=100, metadata=doc("function evaluations per run"))
    restarts: int = field(default=2, metadata=doc("runs in all, the first from the current ψ"))
    perturbation: float = field(default=0.1, metadata=doc(PERTURBATION_HELP))
    batched: bool = field(default=True, metadata=doc(BATCHED_HELP))


@dataclass
class PlateauConfig:
    """MC-PILCO's plateau rule (qtl/plateau.py): |smoothed signal-to-noise of ΔV| below a threshold for a window."""

    ema: float = field(default=0.99, metadata=doc("EMA factor of the change statistics"))
    threshold: float = field(default=0.08, metadata=doc("plateau when |ratio| stays below this (halved each plateau)"))
    window: int = field(default=200, metadata=doc("for this many steps"))
    min_steps: int = field(default=200, metadata=doc("no plateau before this many steps"))


@dataclass
class AdamConfig(OptimizerConfig):
    """Policy search by Adam (for stochastic objectives such as particle rollouts)."""

    _target_: str = "qtl.policy_search.AdamSearch"
    steps: int = field(default=300, metadata=doc("Adam steps per run"))
    lr: float = field(default=0.01, metadata=doc("learning rate"))
    restarts: int = field(default=1, metadata=doc("runs in all, the first from the current ψ"))
    perturbation: float = field(default=0.1, metadata=doc(PERTURBATION_HELP))
    batched: bool = field(default=True, metadata=doc(BATCHED_HELP))
    keep: str = field(
        default="best",
        metadata=doc("best | last | validated: the ψ a run leaves (last: for noisy objectives; validated: the best "
                     "of the start, 20 snapshots along the run and the last, each valued afresh)"),
    )
    dropout: float = field(
        default=0.0, metadata=doc("policy basis dropout during the search (MC-PILCO; policy=rbf_network, particles)"),
    )
    dropout_reduction: float = field(default=0.125, metadata=doc("dropout lowered by this at each plateau"))
    plateau: Optional[PlateauConfig] = field(  # noqa: UP045
        default=None, metadata=doc("MC-PILCO's plateau rule (null: a fixed number of steps)"),
    )
    lr_reduction: float = field(default=0.5, metadata=doc("learning rate × this at each plateau"))
    lr_min: float = field(default=0.0025, metadata=doc("a plateau at this learning rate ends the run"))
    lr_scales: dict[str, float] = field(
        default_factory=dict,
        metadata=doc("learning rate × factor per part of ψ by name, e.g. +optimizer.lr_scales.support_points=0.05"),
    )


@dataclass
class RuleConfig:
    """Base of the ``rule`` options: how θ_i follows θ_p_i (qtl/transfer/rules.py)."""

    _target_: str = MISSING


@dataclass
class NoTransferConfig(RuleConfig):
    """PILCO: θ_i = θ_p_i, evidence maximisation each episode; θ_s is not used."""

    _target_: str = "qtl.transfer.NoTransfer"
    space: str = field(default="log", metadata=doc(SPACE_HELP))


@dataclass
class FreeConfig(RuleConfig):
    """Hyper-parameters transfer: θ_s for the first model, then θ_p re-learned freely (from θ_s)."""

    _target_: str = "qtl.transfer.Free"
    space: str = field(default="log", metadata=doc(SPACE_HELP))


@dataclass
class ForgettingConfig(RuleConfig):
    """Forgetting factor: θ_0 = θ_s, θ_i = γ θ_{i−1} + (1 − γ) θ_p_i (Eq. 6-7)."""

    _target_: str = "qtl.transfer.Forgetting"
    space: str = field(default="log", metadata=doc(SPACE_HELP))
    gamma: float = field(default=0.9, metadata=doc("γ in [0, 1]: 0 is PILCO, 1 keeps θ_s"))


@dataclass
class BayesianConfig(RuleConfig):
    """Bayesian updating (Eq. 8-12): per hyper-parameter, N(θ_s, σ_0²) fused with each θ_p ~ N(θ, c / n)."""

    _target_: str = "qtl.transfer.Bayesian"
    space: str = field(default="log", metadata=doc(SPACE_HELP))
    source_variance: float = field(default=1.0, metadata=doc("σ_0²: the prior variance of θ_s"))
    evidence_variance: float = field(default=100.0, metadata=doc("c in σ_p² = c / n (Eq. 12)"))


@dataclass
class ModelConfig:
    """Base of the ``model`` options: which dynamics GP the loop fits (qtl/models/fitting.py), and its fit."""

    _target_: str = MISSING
    restarts: int = field(
        default=DEFAULT_RESTARTS, metadata=doc("evidence maximisation: L-BFGS runs, the best kept per output"),
    )
    max_iter: int = field(default=DEFAULT_MAX_ITER, metadata=doc("L-BFGS iterations per run"))
    warm_start: bool = field(
        default=True,
        metadata=doc("start each fit from the previous episode's θ_p (and Z), the cold restarts only for outputs "
                     "whose evidence per point falls short of the previous fit's (the first fit: θ_s or heuristic)"),
    )


@dataclass
class ExactModelConfig(ModelConfig):
    """The exact GP at every data size."""

    _target_: str = "qtl.models.ExactFit"


@dataclass
class SparseModelConfig(ModelConfig):
    """The sparse GP (SGPR, inducing inputs learned with θ) at every data size."""

    _target_: str = "qtl.models.SparseFit"
    inducing: int = field(default=DEFAULT_INDUCING, metadata=doc(INDUCING_HELP))
    inducing_jitter: float = field(default=DEFAULT_JITTER, metadata=doc(INDUCING_JITTER_HELP))


@dataclass
class AutoModelConfig(ModelConfig):
    """The exact GP up to ``sparse_above`` tuples, the sparse GP above (the default)."""

    _target_: str = "qtl.models.AutoFit"
    sparse_above: Optional[int] = field(  # noqa: UP045
        default=DEFAULT_SPARSE_ABOVE, metadata=doc("more tuples than this: the sparse GP (null: always exact)"),
    )
    inducing: int = field(default=DEFAULT_INDUCING, metadata=doc(INDUCING_HELP))
    inducing_jitter: float = field(default=DEFAULT_JITTER, metadata=doc(INDUCING_JITTER_HELP))


# The group options and their schemas: `configs/<group>/<option>.yaml` names `<option>_schema` first.
GROUP_SCHEMAS: dict[str, dict[str, type]] = {
    "propagation": {"moment_matching": MomentMatchingConfig, "particles": ParticlesConfig},
    "policy": {"rbf": RBFPolicyConfig, "rbf_network": RBFNetworkPolicyConfig, "linear": LinearPolicyConfig},
    "optimizer": {"lbfgs": LBFGSConfig, "adam": AdamConfig},
    "rule": {"none": NoTransferConfig, "free": FreeConfig, "forgetting": ForgettingConfig, "bayesian": BayesianConfig},
    "model": {"auto": AutoModelConfig, "exact": ExactModelConfig, "sparse": SparseModelConfig},
}
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


SCHEMA_BY_TARGET: dict[str, type] = {
    schema._target_: schema for options in GROUP_SCHEMAS.values() for schema in options.values()  # type: ignore[attr-defined]
}


def typed_groups(cfg: DictConfig) -> DictConfig:
    """``cfg`` with each group node merged onto the schema of its option (by ``_target_``): defaults filled, checked.

    A stored run config (a checkpoint's) then compares and merges like a freshly composed one.
    """
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


def check_group_keys(cfg: DictConfig) -> None:
    """Every key of a group node is a key of its option's schema (``+group.key=...`` gets past Hydra's check)."""
    for group in GROUP_SCHEMAS:
        node = cfg.get(group)
        schema = None if node is None else SCHEMA_BY_TARGET.get(node.get("_target_"))
        if schema is None:
            continue
        known = {f.name for f in dataclasses.fields(schema)}
        unknown = sorted(set(node) - known)
        if unknown:
            raise UserError(
                f"{group}.{unknown[0]} is no key of {group} {node._target_}: its keys are "
                f"{sorted(k for k in known if not k.startswith('_'))}"
            )


# -- the rest ------------------------------------------------------------------------------------


@dataclass
class TransferConfig:
    """Transfer from a source run (Algorithm 1): what is transferred and the compliance gate."""

    source: Optional[str] = field(  # noqa: UP045
        default=None, metadata=doc("a finished run directory of the source task"),
    )
    hyperparameters: bool = field(
        default=True, metadata=doc("θ_0 = θ_s, then the rule (rule=free|forgetting|bayesian)"),
    )
    policy: bool = field(default=False, metadata=doc("ψ_0 = ψ_s: the source's final policy is the initial policy"))
    min_compliance: Optional[float] = field(  # noqa: UP045
        default=None, metadata=doc("below this task compliance (Eq. 14) at the first model, fall back to PILCO"),
    )
    compliance: str = field(
        default="kernel",
        metadata=doc("kernel | likelihood_ratio: Eq. 14 after Lazaric et al.'s kernel estimate, the source GP's "
                     "predictive smoothed by Scott's bandwidth, or as a tempered source-vs-target likelihood ratio "
                     "(docs/dev/compliance-notes.md)"),
    )
    compliance_temperature: Optional[float] = field(  # noqa: UP045
        default=None, metadata=doc("κ of Eq. 14 (null: the state dimension; likelihood_ratio only)"),
    )
    compliance_resolution: float = field(
        default=0.0, metadata=doc("ρ: compare at ρ × each output's spread of Δ (0: exact)"),
    )
    compliance_bandwidth: str = field(
        default="scott",
        metadata=doc("scott | none: the kernel compliance's density bandwidth, Scott's rule on the source's Δ "
                     "(kernel only; docs/dev/compliance-notes.md)"),
    )


@dataclass
class KernelsConfig:
    """How the shared kernel maths runs (``qtl.kernels``)."""

    backend: str = field(
        default="auto",
        metadata=doc("torch | auto | native: the fused exp sums of moment matching (native: C, CPU float64; "
                     "auto: native when built, else torch)"),
    )
    moments: str = field(
        default="auto",
        metadata=doc("reference | fused | native | auto: the moment-matching maths (fused: ~45% fewer torch "
                     "ops per step, the same moments to ~1e-13; native: fused with its hot pieces compiled, "
                     "needs the native build; auto: native when built, else fused; round-off differs, so "
                     "metrics.csv is per formulation)"),
    )


@dataclass
class SweepConfig:
    """Where an experiment preset (``configs/experiment/``) puts its source and target runs."""

    name: Optional[str] = field(default=None, metadata=doc("the experiment's name"))  # noqa: UP045
    root: str = field(default="runs/experiments", metadata=doc("directory of the experiment's runs"))


@dataclass
class TrainConfig:
    """Top level of ``qtl-train``."""

    task: TaskConfig = field(default=MISSING, metadata=doc("the task (group task=...)"))
    propagation: PropagationConfig = field(
        default=MISSING, metadata=doc("long-term prediction (group propagation=...)"),
    )
    policy: PolicyConfig = field(default=MISSING, metadata=doc("the policy π_ψ (group policy=...)"))
    optimizer: OptimizerConfig = field(default=MISSING, metadata=doc("policy search (group optimizer=...)"))
    rule: RuleConfig = field(default=MISSING, metadata=doc("how θ_i follows θ_p_i (group rule=...)"))
    seed: int = field(default=0, metadata=doc("seed of every random stream"))
    random_episodes: int = field(default=1, metadata=doc("initial episodes (random actions, or π(ψ_s)); >= 1"))
    episodes: int = field(default=9, metadata=doc("learned episodes after them; >= 0"))
    device: str = field(default="cpu", metadata=doc("cpu | cuda | cuda:N"))
    threads: Optional[int] = field(  # noqa: UP045
        default=None, metadata=doc("torch intra-op threads (null: torch's default; 1 in multirun)"),
    )
    dtype: str = field(default="float64", metadata=doc("float64 | float32"))
    resume: Optional[str] = field(  # noqa: UP045
        default=None, metadata=doc("a run directory to continue; auto: this run's own, if any"),
    )
    progress: Optional[bool] = field(  # noqa: UP045
        default=None, metadata=doc("progress bars (null: on when stderr is a terminal)"),
    )
    figure_every: int = field(
        default=3, metadata=doc("predicted-vs-real figure every this many learned episodes (0: never)"),
    )
    keep_checkpoints: int = field(
        default=0, metadata=doc("keep only the newest this many episode checkpoints (0: all; resume needs 1)"),
    )
    model: ModelConfig = field(default=MISSING, metadata=doc("the dynamics GP and its fit (group model=...)"))
    transfer: TransferConfig = field(
        default_factory=TransferConfig, metadata=doc("transfer from a source run (Section 4)"),
    )
    sweep: SweepConfig = field(default_factory=SweepConfig, metadata=doc("where an experiment preset puts its runs"))
    kernels: KernelsConfig = field(default_factory=KernelsConfig, metadata=doc("the kernel maths' engine"))


# -- checks Hydra cannot make ------------------------------------------------------------------------


def check_budget(cfg: DictConfig) -> None:
    """Episode counts a run can learn from; a one-line :class:`UserError` otherwise."""
    if cfg.random_episodes < 1:
        raise UserError(
            f"random_episodes={cfg.random_episodes}: the first model needs data, so random_episodes must be >= 1 "
            "(the initial episodes apply random actions, or π(ψ_s) with transfer.policy=true)"
        )
    if cfg.episodes < 0:
        raise UserError(f"episodes={cfg.episodes}: the learned episodes after the initial ones must be >= 0")
    if cfg.keep_checkpoints < 0:
        raise UserError(f"keep_checkpoints={cfg.keep_checkpoints}: keep the newest N >= 1 checkpoints, or 0 for all")


def show_progress(setting: bool | None) -> bool:
    """``progress``: as set, or (null) on exactly when stderr is a terminal."""
    return sys.stderr.isatty() if setting is None else bool(setting)


def run_dir(resume: str | None, default: str) -> str:
    """Hydra's run directory: the run being resumed (logs append to its own), else ``default``.

    A ``resume`` directory that does not exist is refused here, before Hydra creates it.
    """
    if resume is None or resume == "auto":
        return default
    path = os.path.abspath(os.path.expanduser(resume))
    if not os.path.isdir(path):
        raise UserError(f"resume={resume!r} does not exist: give the directory of an interrupted run")
    return path


# -- --help --------------------------------------------------------------------------------------------


def _dataclass_of(hint: object) -> type | None:
    """The dataclass a field's type names, ``Optional[...]`` unwrapped; None for a leaf."""
    for candidate in (hint, *typing.get_args(hint)):
        if isinstance(candidate, type) and dataclasses.is_dataclass(candidate):
            return candidate
    return None


def _keys(schema: type, prefix: str = "") -> Iterator[tuple[str, str, str]]:
    """(dotted key, default, description) of every leaf of ``schema``, nested dataclasses expanded."""
    hints = typing.get_type_hints(schema)
    for f in dataclasses.fields(schema):
        if f.name.startswith("_") or (not prefix and f.name in GROUP_SCHEMAS):
            continue  # `_target_` and friends; the groups are listed per option
        key = f"{prefix}{f.name}"
        nested = _dataclass_of(hints[f.name])
        if nested is not None:
            yield from _keys(nested, f"{key}.")
            continue
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        shown = OmegaConf.to_yaml({"v": default}).strip().removeprefix("v:").strip()
        yield key, shown, f.metadata.get("help", "")


def _entry(key: str, default: str, text: str, indent: str) -> str:
    """One aligned line of the key list (two when the key is long)."""
    head = f"{indent}{key} [{default}]"
    return f"{head:<{HELP_WIDTH}} {text}" if len(head) < HELP_WIDTH else f"{head}\n{'':<{HELP_WIDTH}} {text}"


def help_text() -> str:
    """The key list of ``qtl-train --help``: every key with its default and description, then each group's options."""
    lines = ["== Keys (key=value; defaults in brackets) =="]
    lines += [_entry(key, default, text, "  ") for key, default, text in _keys(TrainConfig)]
    for group, options in GROUP_SCHEMAS.items():
        lines += ["", f"== {group}=<option> =="]
        for option, schema in options.items():
            lines.append(f"  {group}={option}: {_summary(schema)}")
            lines += [_entry(key, default, text, "    ") for key, default, text in _keys(schema, f"{group}.")]
    return "\n".join(lines)


def _summary(schema: type) -> str:
    """A group option's one-line description: its schema's docstring."""
    return (schema.__doc__ or "").strip()


# -- the installed config groups ---------------------------------------------------------------------------

CONFIG_PACKAGE = "qtl.configs"
SCHEMA_SUFFIX = "_schema"  # ConfigStore entries that type an option: no choice of their own
_PACKAGE_LINE = re.compile(r"#\s*@package\b")
# The end of a YAML comment's first sentence: a full stop before a capital or the end, not "Eq." or "Fig.".
_SENTENCE_END = re.compile(r"(?<!\bEq)(?<!\bFig)(?<!\bTab)\.(?=\s+[A-Z]|\s*$)")
SUMMARY_LENGTH = 160  # a longer first sentence is cut at its first clause


def _first_clause(sentence: str) -> str:
    """``sentence`` up to its first ``:`` or ``;`` outside parentheses and brackets, as a sentence."""
    depth = 0
    for i, char in enumerate(sentence):
        depth += (char in "([") - (char in ")]")
        if depth == 0 and char in ":;" and sentence[i + 1 : i + 2] == " ":
            return sentence[:i] + "."
    return sentence


def _comment_summary(text: str) -> str:
    """The first sentence of a YAML file's leading comment (``# @package`` lines skipped); empty without one.

    A sentence longer than :data:`SUMMARY_LENGTH` is cut at its first clause.
    """
    parts: list[str] = []
    for line in text.splitlines():
        if not line.startswith("#"):
            break
        if not _PACKAGE_LINE.match(line):
            parts.append(line.lstrip("#").strip())
    comment = " ".join(part for part in parts if part)
    end = _SENTENCE_END.search(comment)
    sentence = comment if end is None else comment[: end.end()]
    return _first_clause(sentence) if len(sentence) > SUMMARY_LENGTH else sentence


def config_groups() -> dict[str, list[tuple[str, str]]]:
    """Each group of the installed config tree with its options and their one-line descriptions, by name.

    The options are the group's YAML files (``qtl.configs/<group>/<option>.yaml``), each described by the first
    sentence of its leading comment; the ``<option>_schema`` entries that type them in the ConfigStore are not
    choices. Hydra's own groups (``hydra/...``) are left out, as Hydra's ``--help`` leaves them out.
    """
    groups: dict[str, list[tuple[str, str]]] = {}
    for folder in sorted(importlib.resources.files(CONFIG_PACKAGE).iterdir(), key=lambda entry: entry.name):
        if not folder.is_dir() or folder.name == "hydra":
            continue
        options = [
            (file.name.removesuffix(".yaml"), _comment_summary(file.read_text(encoding="utf-8")))
            for file in sorted(folder.iterdir(), key=lambda entry: entry.name)
            if file.name.endswith(".yaml") and not file.name.removesuffix(".yaml").endswith(SCHEMA_SUFFIX)
        ]
        if options:
            groups[folder.name] = options
    return groups


def default_options() -> dict[str, str | None]:
    """The option ``train.yaml`` chooses for each group (None: no option unless one is given)."""
    train = OmegaConf.load(importlib.resources.files(CONFIG_PACKAGE).joinpath("train.yaml").open(encoding="utf-8"))
    chosen: dict[str, str | None] = {}
    for entry in train.defaults:
        if isinstance(entry, DictConfig):
            for group, option in entry.items():
                if "/" not in str(group) and not str(group).startswith("override"):
                    chosen[str(group)] = option
    return chosen


def groups_text() -> str:
    """The group list of ``qtl-train --help``: ``group: option, option, ...`` per installed group."""
    return "\n".join(f"{group}: {', '.join(name for name, _ in options)}" for group, options in config_groups().items())


# -- the configuration reference (docs/guide/configuration.md) ------------------------------------------------

REFERENCE_PAGE = "docs/guide/configuration.md"
REFERENCE_COMMAND = f"python -m qtl.config --markdown > {REFERENCE_PAGE}"
REFERENCE_INTRO = """\
# Configuration reference

Every key `qtl-train` reads, with its default and its meaning: the list `qtl-train --help` prints, from the same
schema (the dataclasses of `qtl/config.py`). Choose a group's option with `group=option` and set a key with
`key=value`, e.g. `qtl-train task=mountaincar task.env.power=0.5 optimizer=adam optimizer.lr=0.005`; a key the
schema does not know, or a value of the wrong type, fails before any work. `???` marks a key without a default
(the task file or the option sets it), `${key}` a default read from another key, `null` an unset optional value.
"""


def _cell(text: str) -> str:
    """``text`` safe in a Markdown table cell: pipes escaped, no emphasis or HTML read into it."""
    return text.replace("\\", "\\\\").replace("|", "\\|").replace("*", "\\*").replace("<", "&lt;")


def _code(text: str) -> str:
    """``text`` as an inline code span (a pipe inside one does not split a table cell; a backtick lengthens it)."""
    fence = "``" if "`" in text else "`"
    pad = " " if text.startswith("`") or text.endswith("`") else ""
    return f"{fence}{pad}{text}{pad}{fence}"


def _key_table(rows: list[tuple[str, str, str]]) -> list[str]:
    """The ``key | default | meaning`` table of ``rows`` (dotted key, default, description)."""
    lines = ["| key | default | meaning |", "| --- | --- | --- |"]
    lines += [f"| {_code(key)} | {_code(default)} | {_cell(text)} |" for key, default, text in rows]
    return lines


def _option_table(group: str, options: list[tuple[str, str]], default: str | None) -> list[str]:
    """The ``option | description`` table of a group, its default option marked."""
    lines = ["| option | description |", "| --- | --- |"]
    for name, text in options:
        mark = " (default)" if name == default else ""
        lines.append(f"| {_code(f'{group}={name}')}{mark} | {_cell(text)} |")
    return lines


def _heading_text(text: str) -> str:
    """A field's description as a sentence under its section's heading."""
    text = _cell(text)
    return f"{text[:1].upper()}{text[1:]}."


def reference_markdown() -> str:
    """The configuration reference page: the keys of ``--help`` (the same walk, the same text), a section per group.

    Top-level keys first, then a section per node of :class:`TrainConfig` in its order (``task``, the groups with a
    table per option, ``transfer``, ``sweep``, ``kernels``), then the preset groups (``approach``, ...).
    """
    keys = list(_keys(TrainConfig))
    groups = config_groups()
    defaults = default_options()
    hints = typing.get_type_hints(TrainConfig)
    lines = [f"<!-- Generated by `{REFERENCE_COMMAND}` from qtl/config.py: edit there, not here. -->", "",
             REFERENCE_INTRO, "## Config groups", "", "| group | options | default |", "| --- | --- | --- |"]
    for group, options in groups.items():
        chosen = defaults.get(group)
        names = ", ".join(_code(name) for name, _ in options)
        lines.append(f"| {_code(group)} | {names} | {_code('null' if chosen is None else chosen)} |")
    lines += ["", "## Top-level keys", "", *_key_table([row for row in keys if "." not in row[0]])]
    nodes = [f for f in dataclasses.fields(TrainConfig)
             if f.name in GROUP_SCHEMAS or f.name in groups or _dataclass_of(hints[f.name]) is not None]
    for node in nodes:
        lines += ["", f"## {node.name}", "", _heading_text(node.metadata.get("help", ""))]
        if node.name not in GROUP_SCHEMAS:
            if node.name in groups:
                lines += ["", *_option_table(node.name, groups[node.name], defaults.get(node.name))]
            lines += ["", *_key_table([row for row in keys if row[0].startswith(f"{node.name}.")])]
            continue
        if defaults.get(node.name) is not None:
            lines[-1] += f" Default: `{node.name}={defaults[node.name]}`."
        for option, schema in GROUP_SCHEMAS[node.name].items():
            rows = list(_keys(schema, f"{node.name}."))
            lines += ["", f"### {node.name}={option}", "", _cell(_summary(schema)), ""]
            lines += _key_table(rows) if rows else ["No keys of its own."]
    presets = [group for group in groups if group not in {node.name for node in nodes}]
    if presets:
        lines += ["", "## Presets", "", "Groups whose options set keys of several nodes at once "
                  "(`# @package _global_`), applied over `train.yaml`."]
        for group in presets:
            lines += ["", f"### {group}", "", *_option_table(group, groups[group], defaults.get(group))]
    return "\n".join(lines) + "\n"


HELP_TEMPLATE = """\
qtl-train: learn a task with PILCO, from scratch or with qualitative transfer from a source run.

  qtl-train [group=option ...] [key=value ...]      e.g. qtl-train task=mountaincar task.env.power=0.5 seed=3
  qtl-train resume=<run dir> [episodes=N]           continue an interrupted run
  qtl-train --cfg job [overrides]                   print the composed config

== Config groups (group=option) ==
{groups}

{keys}

Bad input fails before any work with one line saying what to fix (HYDRA_FULL_ERROR=1: the traceback).
Hydra's own flags: --hydra-help
"""


def register_configs() -> None:
    """Register the schema, each group option's schema, the run-directory resolver and the ``--help`` text."""
    store = ConfigStore.instance()
    store.store(name="train_schema", node=TrainConfig)
    for group, options in GROUP_SCHEMAS.items():
        for option, schema in options.items():
            store.store(group=group, name=f"{option}_schema", node=schema)
    # `$` would be read as Hydra's template placeholders and `${` as OmegaConf interpolations.
    keys = help_text().replace("$", "$$").replace("${", "\\${")
    groups = groups_text().replace("$", "$$").replace("${", "\\${")
    store.store(group="hydra/help", name="qtl",
                node={"app_name": "qtl-train", "template": HELP_TEMPLATE.format(keys=keys, groups=groups)})
    if not OmegaConf.has_resolver(RUN_DIR_RESOLVER):
        OmegaConf.register_new_resolver(RUN_DIR_RESOLVER, run_dir)


def main(argv: list[str] | None = None) -> None:
    """``python -m qtl.config --markdown``: print the configuration reference page (else the ``--help`` key list)."""
    args = sys.argv[1:] if argv is None else argv
    if args not in ([], ["--markdown"]):
        raise SystemExit(f"usage: {REFERENCE_COMMAND}")
    sys.stdout.reconfigure(encoding="utf-8")  # type: ignore[union-attr]
    sys.stdout.write(reference_markdown() if args else help_text() + "\n")


if __name__ == "__main__":
    main()
