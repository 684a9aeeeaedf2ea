"""One schema per option of the ``propagation``, ``policy``, ``optimizer``, ``rule`` and ``model`` groups.

Each is stored as ``<group>/<option>_schema`` in the ConfigStore and named first in the option's defaults
list, so that a key the option does not have, or a value of the wrong type, fails at compose time.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from omegaconf import II

from qtl.config.schema import ModelConfig, OptimizerConfig, PolicyConfig, PropagationConfig, RuleConfig, doc
from qtl.models.fitting import DEFAULT_INDUCING, DEFAULT_JITTER, DEFAULT_SPARSE_ABOVE
from qtl.propagation.particles import DEFAULT_NUM_FEATURES

PERTURBATION_HELP = "std of the restarts' perturbation, relative to each parameter's spread"
BATCHED_HELP = ("all restarts at once: one batched rollout evaluates every running restart, each restart keeps its "
                "own optimiser (L-BFGS: the sequential run, in lockstep) (false: one restart after the other)")
SPACE_HELP = "log | natural: the space θ is handled in"
INDUCING_HELP = "inducing inputs of the sparse GP (PILCO's FITC uses ~300)"
INDUCING_JITTER_HELP = "the sparse GP's jitter on K_mm's diagonal, a fraction of α² (0: none)"
INTEGRATION_HELP = ("delta | speed: x + Δ in every dimension, or the GP's Δ of the velocities (and other non-position "
                    "dims) with positions integrated, q + T q̇ + (T/2) Δq̇ (MC-PILCO; task.kinematics)")


@dataclass
class MomentMatchingConfig(PropagationConfig):
    """Analytic moment matching through policy and GP (PILCO; Eq. 1-5)."""

    _target_: str = "qtl.propagation.MomentMatching"
    include_noise: bool = field(default=False, metadata=doc("add the GP's noise variance to every predicted state"))
    integration: str = field(
        default="delta", metadata=doc(INTEGRATION_HELP + "; speed evaluates the GP on the modelled outputs only "
                                      "(fewer output pairs: faster), its moments exact"),
    )
    survival: str = field(
        default="markov",
        metadata=doc("markov | product: with terminate constraints, the probability of having stayed inside from each "
                     "consecutive pair's bivariate Gaussian (markov), or the product of the steps' marginals "
                     "(product, Safe-PILCO's; pessimistic)"),
    )


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
    integration: str = field(default="delta", metadata=doc(INTEGRATION_HELP))
    search_start_scale: float = field(
        default=1.0, metadata=doc("the search's start spread: N(μ_0, s² Σ_0), s in (0, 1] (lower gradient variance "
                                  "on chaotic rollouts; predictions keep the task's start)"),
    )
    seed: int = field(default=II("seed"), metadata=doc("seed of the base noise"))


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
# Each option's schema by its `_target_`: how a stored or composed group node is typed and checked.
SCHEMA_BY_TARGET: dict[str, type] = {
    schema._target_: schema for options in GROUP_SCHEMAS.values() for schema in options.values()  # type: ignore[attr-defined]
}
