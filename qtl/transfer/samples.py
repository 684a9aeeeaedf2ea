"""Source samples weighted by relevance: source tuples in the target GP's data with noise σ_ε² / w (issue 65).

The paper's conclusion names the step beyond θ: tuples of the source that adjust the target's posterior of the
transition function. Lazaric et al. (2008) weigh each source sample by its *relevance*: its own compliance with the
target's samples where those can judge it, combined with the whole task's compliance. qtl uses the GP-native form of
that idea. With the target GP f_T fitted on the target's tuples alone at the current θ, source tuple (x_i, Δ_i) has,
for output e,

- a local relevance, its predictive density over the density's peak,
  ℓ_ei = N(Δ_ei; μ_e(x_i), v_e(x_i) + σ_e²) / N(μ_e(x_i); μ_e(x_i), v_e(x_i) + σ_e²) = exp(−½ z_ei²);
- a coverage κ_ei = 1 − v_e(x_i)/α_e² ∈ [0, 1]: how far the target's tuples have pinned f_T down at x_i (0 far from
  them, where f_T is its prior and ℓ says nothing);
- the source's trust for that output, ρ_e = (√2 Σ_i κ_ei ℓ_ei + 1) / (Σ_i κ_ei + 1) capped at 1: the covered
  tuples' mean ℓ over what a source that matches the target scores (E[exp(−½ z²)] = 1/√2 for z ~ N(0, 1); a source
  off by b standard deviations scores exp(−b²/4)), with one pseudo-tuple of full trust before there is coverage;

and w_ei = κ_ei ℓ_ei + (1 − κ_ei) ρ_e. Where the target's tuples contradict the source, ℓ → 0; where the target has no
data, a tuple counts as much as the source has earned where it could be judged, so a source that contradicts the
target where it has been is switched off where it has not. The tuple joins the target's data with noise
σ_e² + σ̂_e² (1/w_ei − 1), σ̂_e² the noise of the judging θ, so σ_e²/w_ei there (:mod:`qtl.models.point_noise`): w = 1
pools it, w → 0 leaves the target's data alone, for the posterior and for evidence maximisation of θ alike. Per
output, since the outputs are independent GPs. The weights are recomputed at every model, so the target's data take
over as they grow.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from qtl.data import TransitionDataset, gp_training_pairs
from qtl.models import DynamicsGP, GPHyperparameters

# transfer.samples: no source tuples (θ and ψ only), or source tuples weighted by relevance.
SAMPLE_MODES = ("none", "relevance")
# The floor of w: σ_ε² / w stays finite and K well conditioned; such a tuple moves the posterior by ~w of its residual.
MIN_RELEVANCE = 1e-8
# ρ's prior: this many tuples of full trust, so that ρ = 1 before the target's tuples cover any source tuple.
TRUST_PSEUDO_TUPLES = 1.0
# metrics.csv columns (runs with transfer.samples=relevance only): the source tuples in the GP's data, the mean w over
# them and the outputs, and Σ_i w_i averaged over the outputs (the effective number of source tuples).
SOURCE_SAMPLES = "source_samples"
RELEVANCE = "relevance"
EFFECTIVE_SAMPLES = "effective_samples"
SAMPLE_COLUMNS = (SOURCE_SAMPLES, RELEVANCE, EFFECTIVE_SAMPLES)


def local_relevance(target: DynamicsGP, source_x: Tensor, source_y: Tensor) -> tuple[Tensor, Tensor]:
    """ℓ = exp(−½ z²) and coverage κ = 1 − v/α² of source tuples `N x D`, `N x E` under ``target``: `N x E` each."""
    mean, variance = target.predict(source_x, include_noise=True)
    local = torch.exp(-0.5 * (source_y - mean).square() / variance)
    theta = target.hyperparameters
    latent = variance - theta.noise_variance.to(variance)
    coverage = (1 - latent / theta.signal_variance.to(variance)).clamp(0.0, 1.0)
    return local, coverage


def source_trust(local: Tensor, coverage: Tensor) -> Tensor:
    """ρ_e = (√2 Σ κ ℓ + 1) / (Σ κ + 1) ≤ 1 of ℓ, κ `N x E`: the covered tuples' ℓ over a matching source's: `E`."""
    earned = math.sqrt(2.0) * (coverage * local).sum(0) + TRUST_PSEUDO_TUPLES
    return (earned / (coverage.sum(0) + TRUST_PSEUDO_TUPLES)).clamp(max=1.0)


def judged_relevance(judge: DynamicsGP, source_x: Tensor, source_y: Tensor) -> Tensor:
    """w = κ ℓ + (1 − κ) ρ of source tuples `N x D`, `N x E` under ``judge``, a GP of the target's tuples: `N x E`."""
    local, coverage = local_relevance(judge, source_x, source_y)
    weights = coverage * local + (1 - coverage) * source_trust(local, coverage)
    return weights.clamp(MIN_RELEVANCE, 1.0)


def relevance(target_x: Tensor, target_y: Tensor, source_x: Tensor, source_y: Tensor,
              theta: GPHyperparameters) -> Tensor:
    """:func:`judged_relevance` under the GP at θ of the target's tuples `n x D`, `n x E`: `N x E`."""
    return judged_relevance(DynamicsGP(target_x, target_y, theta, dtype=target_x.dtype), source_x, source_y)


@dataclass(frozen=True)
class WeightedSamples:
    """Source tuples for the target's GP: inputs `N x D`, targets Δ `N x E` (modelled outputs), relevance `N x E`.

    ``judged_noise``: σ̂_ε² `E`, the noise of the θ the relevance was computed at.
    """

    inputs: Tensor
    targets: Tensor
    weights: Tensor
    judged_noise: Tensor

    @property
    def extra_noise(self) -> Tensor:
        """c = σ̂_ε² (1/w − 1) `N x E`: noise σ_ε² + c, σ_ε²/w at the judging θ (:mod:`qtl.models.point_noise`)."""
        return self.judged_noise * (self.weights.reciprocal() - 1)

    def row(self) -> dict[str, float]:
        """The ``metrics.csv`` columns of these samples: count, mean w, Σ w averaged over the outputs."""
        return {SOURCE_SAMPLES: float(len(self.inputs)), RELEVANCE: float(self.weights.mean()),
                EFFECTIVE_SAMPLES: float(self.weights.sum(0).mean())}


@dataclass(frozen=True)
class SourceSamples:
    """Up to ``max_samples`` tuples of a source run's data, evenly spaced over it: inputs `N x D`, targets `N x E`.

    ``indices`` `N`: which of the source's tuples (in its dataset's order); ``outputs``: the state dimensions of the
    target columns (the target's modelled outputs).
    """

    inputs: Tensor
    targets: Tensor
    indices: Tensor
    outputs: tuple[int, ...]

    @classmethod
    def of(cls, dataset: TransitionDataset, features: Callable[[Tensor], Tensor], outputs: Sequence[int],
           max_samples: int, dtype: torch.dtype = torch.float64,
           device: torch.device | str = "cpu") -> SourceSamples:
        """The tuples of ``dataset`` as GP training pairs, thinned evenly to ``max_samples`` (all if fewer)."""
        inputs, targets = gp_training_pairs(dataset, features, dtype, device)
        total = len(inputs)
        indices = torch.linspace(0, total - 1, min(total, int(max_samples)), dtype=torch.float64).round().long()
        indices = torch.unique(indices)
        outputs = tuple(int(d) for d in outputs)
        return cls(inputs[indices.to(inputs.device)], targets[:, list(outputs)][indices.to(inputs.device)], indices,
                   outputs)

    def judged_by(self, judge: DynamicsGP) -> WeightedSamples:
        """The samples with their relevance under ``judge``, a GP of the target's tuples alone (of its outputs).

        An output the judge has no GP for (its Δ constant in the target's data) keeps w = 1.
        """
        weights = torch.ones_like(self.targets)
        noise = torch.zeros(len(self.outputs), dtype=self.targets.dtype, device=self.targets.device)
        columns = [self.outputs.index(d) for d in judge.outputs]
        if columns:
            weights[:, columns] = judged_relevance(judge, self.inputs, self.targets[:, columns])
            noise[columns] = judge.hyperparameters.noise_variance.to(noise)
        return WeightedSamples(self.inputs, self.targets, weights, noise)

    def weighted(self, target_x: Tensor, target_y: Tensor, theta: GPHyperparameters,
                 theta_outputs: Sequence[int]) -> WeightedSamples:
        """:meth:`judged_by` the GP at θ (rows ``theta_outputs``) of the target's tuples `n x D`, `n x E` (modelled)."""
        rows = [k for k, d in enumerate(theta_outputs) if d in self.outputs]
        outputs = [int(theta_outputs[k]) for k in rows]
        judged = theta.select(torch.tensor(rows)) if len(rows) != theta.num_outputs else theta
        columns = [self.outputs.index(d) for d in outputs]
        judge = DynamicsGP(target_x, target_y[:, columns], judged.to(dtype=target_x.dtype, device=target_x.device),
                           outputs=outputs, dtype=target_x.dtype)
        return self.judged_by(judge)
