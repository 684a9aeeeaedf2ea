"""Task compliance Λ (Eq. 14): how well the source dynamics GP explains the target's transitions.

After Lazaric, Restelli & Bonarini (ICML 2008). For each target tuple j, with GP input
z_j = [φ(x_j), u_j] and target Δ_j = x_{j+1} − x_j, two hypotheses with equal prior are compared:
the source GP generated Δ_j (its predictive, noise included) or the target GP did (its
leave-one-out predictive, so that the target does not explain its own data trivially). Λ is the
mean over j of the tempered posterior probability of the source hypothesis.

On near-deterministic simulators both predictive variances are tiny, each tuple's log-likelihood
ratio is in the hundreds and Λ saturates at 0 or 1 whatever κ. ``resolution`` ρ compares the two
hypotheses at a finite resolution instead: ρ² s_a² (s_a the standard deviation of output a's Δ
over the target tuples) is added to both predictive variances, so that a source prediction off by
less than about ρ s_a counts as explaining the tuple.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from qtl.models import DynamicsGP

# log(2π), the constant of a Gaussian log density.
LOG_TWO_PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class Compliance:
    """Task compliance Λ and its per-tuple terms (Eq. 14).

    ``value``: Λ, the mean of ``probabilities``; ``probabilities``: `n`, P(S | τ_j);
    ``log_source``: `n`, log p_S(j); ``log_target``: `n`, log p_T(j) (leave-one-out);
    ``temperature``: κ, the tempering of the log-likelihood ratio; ``resolution``: ρ.
    """

    value: float
    probabilities: Tensor
    log_source: Tensor
    log_target: Tensor
    temperature: float
    resolution: float = 0.0


def _gaussian_log_density(y: Tensor, mean: Tensor, variance: Tensor) -> Tensor:
    """Elementwise log N(y; mean, variance) for Eq. 14, all of one shape."""
    return -0.5 * (LOG_TWO_PI + variance.log() + (y - mean).square() / variance)


def leave_one_out(model: DynamicsGP) -> tuple[Tensor, Tensor]:
    """Leave-one-out predictive means and variances `n x E` of the model's own training targets (Eq. 14)."""
    cache = model.exact().posterior_cache()  # leave-one-out needs the n x n solve, not a sparse form
    precision = torch.diagonal(cache.K_inv, dim1=-2, dim2=-1)  # E x n, [K_y⁻¹]_ii
    mean = model.train_y - (cache.beta / precision).T  # n x E, y_i − [K_y⁻¹y]_i / [K_y⁻¹]_ii
    variance = precision.reciprocal().T  # n x E, 1 / [K_y⁻¹]_ii
    return mean, variance


def task_compliance(
    source: DynamicsGP, target: DynamicsGP, *, temperature: float | None = None, resolution: float = 0.0
) -> Compliance:
    """Task compliance Λ of the target model's training tuples under the source model (Eq. 14)."""
    if (source.input_dim, source.num_outputs) != (target.input_dim, target.num_outputs):
        raise ValueError(
            f"source GP has D={source.input_dim} inputs and E={source.num_outputs} outputs, "
            f"target GP has D={target.input_dim} inputs and E={target.num_outputs} outputs: "
            "task compliance needs the same GP input and output dimensions"
        )
    kappa = float(target.num_outputs if temperature is None else temperature)
    if not (math.isfinite(kappa) and kappa > 0):
        raise ValueError(f"temperature must be finite and > 0, got {temperature}")
    if not (math.isfinite(resolution) and resolution >= 0):
        raise ValueError(f"resolution must be finite and >= 0, got {resolution}")

    inputs, deltas = target.train_x, target.train_y  # n x D, n x E
    floor = resolution**2 * deltas.var(dim=0, correction=0) if deltas.shape[0] > 1 else torch.zeros_like(deltas[0])
    # log p_S(j): the source GP's predictive, its own data and θ, noise included.
    source_mean, source_var = source.predict(inputs, include_noise=True)  # n x E each
    log_source = _gaussian_log_density(deltas, source_mean.to(deltas), source_var.to(deltas) + floor).sum(-1)  # n
    # log p_T(j): the target GP's leave-one-out predictive.
    loo_mean, loo_var = leave_one_out(target)  # n x E each
    log_target = _gaussian_log_density(deltas, loo_mean, loo_var + floor).sum(-1)  # n
    # P(S | τ_j) = logistic((log p_S − log p_T) / κ); Λ = mean over j (Eq. 14).
    probabilities = torch.sigmoid((log_source - log_target) / kappa)  # n
    return Compliance(
        value=float(probabilities.mean()),
        probabilities=probabilities,
        log_source=log_source,
        log_target=log_target,
        temperature=kappa,
        resolution=float(resolution),
    )
