"""The dataclass schema of ``qtl-train``'s configuration: a typo or a wrong type fails at compose time.

Every key carries its description beside its field (``metadata["help"]``); ``qtl-train --help`` and the
configuration reference of the docs (``python -m qtl.config --markdown``) list them from the same walk
(:mod:`qtl.config.help`). The groups' bases are here; each option's own schema is in :mod:`qtl.config.groups`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

from omegaconf import MISSING

from qtl.models.fitting import DEFAULT_MAX_ITER, DEFAULT_RESTARTS
from qtl.task import DEFAULT_START_MIN_STD

# OmegaConf reads these annotations at run time: keep `Optional[...]` and `List`-style types
# that it understands (PEP 604 unions are not supported by OmegaConf's structured configs).


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
    # Rows of numbers, an integer as good as a float: OmegaConf 2.3 refuses an int inside a nested float list, so the
    # rows are untyped here and checked by qtl/config/validate.py (check_reward_weight) before any work.
    weight: list[Any] = field(default=MISSING, metadata=doc("weight matrix W of (y-y*)"))
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
    """Which state dimensions are positions and which their velocities (speed integration, propagation.integration)."""

    positions: list[int] = field(default_factory=list, metadata=doc("state indices of the positions q ([]: none)"))
    velocities: list[int] = field(default_factory=list, metadata=doc("state indices of their velocities q̇, in order"))
    period: Optional[float] = field(  # noqa: UP045
        default=None, metadata=doc("control period T in s (null: the env's dt × action_repeat)"),
    )
    weight: float = field(
        default=0.5,
        metadata=doc("w in q_{t+1} = q + T q̇ + w T Δq̇: ½ the trapezoid rule (MC-PILCO), 1 semi-implicit Euler, "
                     "(n+1)/(2n) n semi-implicit Euler steps per decision"),
    )


@dataclass
class ConstraintConfig:
    """A bound on one state dimension (after Safe-PILCO): leaving it ends the episode (terminate) or costs (penalty)."""

    dim: int = field(default=MISSING, metadata=doc("the bounded state dimension (observation coordinates)"))
    low: Optional[float] = field(default=None, metadata=doc("lower bound (null: unbounded below)"))  # noqa: UP045
    high: Optional[float] = field(default=None, metadata=doc("upper bound (null: unbounded above)"))  # noqa: UP045
    kind: str = field(
        default="terminate",
        metadata=doc("terminate (the predicted return weights each step by the survival Π p_t) | penalty (each "
                     "step costs weight × (1 − p_t))"),
    )
    weight: float = field(default=0.0, metadata=doc("penalty only: the cost per step of (1 − p_t), > 0"))


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
    kinematics: KinematicsConfig = field(
        default_factory=KinematicsConfig,
        metadata=doc("positions and velocities, for propagation.integration=speed (positions: []: none)"),
    )
    constraints: list[ConstraintConfig] = field(
        default_factory=list,
        metadata=doc("state bounds that end an episode or cost, in the predicted return (qtl.constraints; []: none)"),
    )
    policy_size: int = field(default=50, metadata=doc("RBF basis functions of the policy"))
    success: SuccessConfig = field(default_factory=SuccessConfig, metadata=doc("when an episode counts as a success"))


# -- the groups' bases: each option's schema (qtl/config/groups.py) extends one -----------------------


@dataclass
class PropagationConfig:
    """Base of the ``propagation`` options: a partial propagator, completed with model, policy and reward."""

    _target_: str = MISSING
    _partial_: bool = True


@dataclass
class PolicyConfig:
    """Base of the ``policy`` options: a partial factory, completed with the dimensions and start features."""

    _target_: str = MISSING
    _partial_: bool = True


@dataclass
class OptimizerConfig:
    """Base of the ``optimizer`` options: a policy search with restarts, the best ψ kept."""

    _target_: str = MISSING


@dataclass
class RuleConfig:
    """Base of the ``rule`` options: how θ_i follows θ_p_i (qtl/transfer/rules.py)."""

    _target_: str = MISSING


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


# -- the rest ------------------------------------------------------------------------------------


@dataclass
class TransferConfig:
    """Transfer from a source run (Algorithm 1): what is transferred and the compliance gate."""

    # Any: a structured config cannot type str | list[str]; check_transfer refuses anything else before any work.
    source: Any = field(
        default=None, metadata=doc("a finished run directory of the source task; a list of them, or a directory "
                                   "whose subfolders are such runs (several sources, chosen by compliance)"),
    )
    select: str = field(
        default="compliance",
        metadata=doc("compliance | mixture: with several sources, θ_s and ψ_s of the most compliant one (Eq. 14), or "
                     "θ_s the Λ-weighted mean of the sources' log θ_s (ψ_s still the most compliant one's)"),
    )
    initial_policy: Optional[str] = field(  # noqa: UP045
        default=None, metadata=doc("with several sources, the source run whose ψ_s acts in the initial episodes (one "
                                   "of the sources; null: random actions)"),
    )
    samples: str = field(
        default="none",
        metadata=doc("none | relevance: up to max_source_samples tuples of the source join each model's data with "
                     "noise σ_ε²/w, w their relevance to the target's tuples (docs/guide/transfer.md)"),
    )
    max_source_samples: int = field(
        default=200, metadata=doc("the most source tuples in the GP's data (evenly spaced over the source's data)"),
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
                     "auto: native where it compiles, else torch)"),
    )
    moments: str = field(
        default="auto",
        metadata=doc("reference | fused | native | auto: the moment-matching maths (fused: ~45% fewer torch "
                     "ops per step, the same moments to ~1e-13; native: fused with its hot pieces compiled, "
                     "needs the native build; auto: native where it compiles, else fused; round-off differs, so "
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
    video: bool = field(
        default=True,
        metadata=doc("with each predicted-vs-real figure, the episode rendered as a TensorBoard video (rollout/video)"),
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
