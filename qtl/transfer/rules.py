"""Hyper-parameter updating rules: θ_i from θ_{i−1} and θ_p_i (Algorithm 1, line 13; Eq. 6-12).

Every rule acts element-wise on θ in its flat `E x (D + 2)` form (``[ℓ_1..ℓ_D, α², σ_ε²]`` per
output dimension), in one of two spaces:

- ``log`` (default): on log θ. θ is positive and spans orders of magnitude (σ_ε² ~ 1e-4 beside
  ℓ ~ 1); in log space a blend is a weighted geometric mean, scale-free and always positive,
  and a Gaussian belief about log θ (Bayesian rule) cannot put mass on θ <= 0.
- ``natural``: on θ itself, as the paper writes Eq. 7 and Eq. 11.

Indexing follows Algorithm 1: θ_0 = θ_s is the θ of the first model of a target run (Eq. 6);
each later model uses θ_i = rule(θ_{i−1}, θ_p_i), with θ_p_i what evidence maximisation found
on all target tuples so far.
"""

from __future__ import annotations

from typing import Any

from torch import Tensor

from qtl.errors import RuleError
from qtl.models import GPHyperparameters

SPACES = ("log", "natural")



def _check_space(space: str) -> str:
    if space not in SPACES:
        raise RuleError(f"rule.space must be one of {list(SPACES)}, got {space!r}")
    return space


def to_space(theta: GPHyperparameters, space: str) -> Tensor:
    """θ as `E x (D + 2)` in ``space`` (log θ or θ)."""
    return theta.log() if space == "log" else theta.natural()


def from_space(values: Tensor, space: str) -> GPHyperparameters:
    """θ from its `E x (D + 2)` form in ``space``."""
    return GPHyperparameters.from_log(values) if space == "log" else GPHyperparameters.from_natural(values)


class HyperparameterRule:
    """θ_i = rule(θ_{i−1}, θ_p_i, n): the base of every rule; holds no state unless it says so.

    ``uses_source``: the rule starts from θ_s (Eq. 6) and needs a source run.
    ``warm_start``: evidence maximisation on the target starts from θ_s instead of PILCO's heuristic.
    """

    name = "rule"
    uses_source = True
    warm_start = False

    def __init__(self, space: str = "log") -> None:
        self.space = _check_space(space)

    def start(self, theta_s: GPHyperparameters) -> GPHyperparameters:
        """θ_0 = θ_s, the θ of the first target model (Eq. 6); resets any state."""
        return theta_s

    def update(self, previous: GPHyperparameters, learned: GPHyperparameters, num_tuples: int) -> GPHyperparameters:
        """θ_i from θ_{i−1} (``previous``), θ_p_i (``learned``) and n target tuples."""
        raise NotImplementedError

    def state_dict(self) -> dict[str, Any]:
        """What a checkpoint must hold to resume the rule."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""

    def describe(self) -> str:
        """The rule and its settings, one line."""
        return f"{self.name} (space={self.space})"


class NoTransfer(HyperparameterRule):
    """PILCO: θ_i = θ_p_i, evidence maximisation from the heuristic each episode; θ_s unused."""

    name = "none"
    uses_source = False

    def start(self, theta_s: GPHyperparameters) -> GPHyperparameters:
        """No θ_0: PILCO has no θ before its first evidence maximisation."""
        raise RuleError("rule=none does not start from θ_s")

    def update(self, previous: GPHyperparameters, learned: GPHyperparameters, num_tuples: int) -> GPHyperparameters:
        """θ_i = θ_p_i."""
        return learned

    def describe(self) -> str:
        """The rule, one line."""
        return "none (PILCO: θ_p each episode)"


class Free(HyperparameterRule):
    """Hyper-parameters transfer: θ_0 = θ_s, then θ_i = θ_p_i re-learned freely from θ_s."""

    name = "free"
    warm_start = True

    def update(self, previous: GPHyperparameters, learned: GPHyperparameters, num_tuples: int) -> GPHyperparameters:
        """θ_i = θ_p_i (evidence maximisation started from θ_s)."""
        return learned

    def describe(self) -> str:
        """The rule, one line."""
        return "free (θ_s first, then θ_p learned from θ_s)"


class Forgetting(HyperparameterRule):
    """θ_0 = θ_s (Eq. 6), θ_i = γ θ_{i−1} + (1 − γ) θ_p_i (Eq. 7): γ = 0 follows θ_p, γ = 1 keeps θ_s."""

    name = "forgetting"

    def __init__(self, gamma: float, space: str = "log") -> None:
        super().__init__(space)
        if not 0.0 <= float(gamma) <= 1.0:
            raise RuleError(f"rule.gamma must be in [0, 1] (0: PILCO's θ_p, 1: keep θ_s), got {gamma}")
        self.gamma = float(gamma)

    def update(self, previous: GPHyperparameters, learned: GPHyperparameters, num_tuples: int) -> GPHyperparameters:
        """θ_i = γ θ_{i−1} + (1 − γ) θ_p_i (Eq. 7)."""
        if self.gamma == 1.0:
            return previous
        if self.gamma == 0.0:
            return learned
        blended = self.gamma * to_space(previous, self.space) + (1.0 - self.gamma) * to_space(learned, self.space)
        return from_space(blended, self.space)

    def describe(self) -> str:
        """The rule and γ, one line."""
        return f"forgetting (γ={self.gamma}, space={self.space})"


class Bayesian(HyperparameterRule):
    """Gaussian fusion of θ_s with each θ_p_k, per hyper-parameter (Eq. 8-12).

    The belief about each hyper-parameter (in ``space``) is N(μ_k, σ_k²), with μ_0 = θ_s and
    σ_0² = ``source_variance``. Each θ_p_k is a noisy observation N(θ, σ_p²) (Eq. 8) whose
    variance shrinks with the n target tuples it was learned from, σ_p² = ``evidence_variance``
    / n (Eq. 12), and the posterior (Eq. 9) is

        σ_k² = σ_p² σ_{k−1}² / (σ_p² + σ_{k−1}²)            (Eq. 10)
        μ_k = σ_k² (μ_{k−1} / σ_{k−1}² + θ_p_k / σ_p²)       (Eq. 11)

    and θ_k = μ_k. The fused mean depends only on the ratio of the two variances: with the
    defaults, an estimate from 100 target tuples weighs as much as θ_s; as n grows θ_k → θ_p.
    In log space the variances read as squared relative errors of θ.
    """

    name = "bayesian"

    def __init__(self, source_variance: float = 1.0, evidence_variance: float = 100.0, space: str = "log") -> None:
        super().__init__(space)
        if not source_variance > 0 or not evidence_variance > 0:
            raise RuleError(
                f"rule.source_variance and rule.evidence_variance must be > 0, "
                f"got {source_variance} and {evidence_variance}"
            )
        self.source_variance = float(source_variance)
        self.evidence_variance = float(evidence_variance)
        self.variance = self.source_variance  # σ_k², the same for every hyper-parameter

    def start(self, theta_s: GPHyperparameters) -> GPHyperparameters:
        """μ_0 = θ_s, σ_0² = ``source_variance`` (Eq. 6)."""
        self.variance = self.source_variance
        return theta_s

    def update(self, previous: GPHyperparameters, learned: GPHyperparameters, num_tuples: int) -> GPHyperparameters:
        """μ_k and σ_k² from μ_{k−1} = θ_{k−1}, σ_{k−1}² and θ_p_k with σ_p² = c / n (Eq. 10-12)."""
        if num_tuples < 1:
            raise RuleError(f"the Bayesian rule needs n >= 1 target tuples, got {num_tuples}")
        evidence = self.evidence_variance / num_tuples  # σ_p², Eq. 12
        posterior = evidence * self.variance / (evidence + self.variance)  # σ_k², Eq. 10
        fused = posterior * (
            to_space(previous, self.space) / self.variance + to_space(learned, self.space) / evidence
        )  # μ_k, Eq. 11
        self.variance = posterior
        return from_space(fused, self.space)

    def state_dict(self) -> dict[str, Any]:
        """σ_k²."""
        return {"variance": self.variance}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore σ_k²."""
        self.variance = float(state["variance"])

    def describe(self) -> str:
        """The rule and its variances, one line."""
        return (f"bayesian (σ_0²={self.source_variance}, σ_p²={self.evidence_variance}/n, "
                f"space={self.space})")

