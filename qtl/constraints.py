"""State constraints of a task (after Safe-PILCO): bounds on state dimensions that end an episode or cost.

A :class:`Constraint` bounds one state dimension ``dim`` (observation coordinates, angles unwrapped) to
[``low``, ``high``] (None: unbounded on that side). ``terminate``: leaving the bounds ends the episode, so the
predicted return weights each step by the probability of having stayed inside so far; ``penalty``: each step
outside costs ``weight``.

The maths, for a Gaussian state x_t ~ N(μ_t, Σ_t) (moment matching) and for particles:

- p_{k,t} = P(l_k ≤ x_{t,d_k} ≤ h_k) = Φ((h_k − μ_{t,d})/σ_{t,d}) − Φ((l_k − μ_{t,d})/σ_{t,d}) from the marginal
  of dimension d_k; several terminate constraints: p_t = Π_k p_{k,t}, the product of the marginals as Safe-PILCO
  takes it (exact for a diagonal Σ_t, an approximation where the constrained dimensions correlate);
- survival: the probability that x_1..x_t all stayed inside. ``product`` (Safe-PILCO): S_t = Π_{τ≤t} p_τ, the steps
  taken as independent; pessimistic, since consecutive states correlate (ρ ~ 0.99 at the cart-pole's 0.1 s).
  ``markov`` (the default): the first-order Markov approximation of the trajectory, S_1 = p_1 and
  S_t = S_{t−1} · P(x_{t−1}, x_t inside) / P(x_{t−1} inside), the pair's probability from the bivariate Gaussian of
  (x_{t−1,d}, x_{t,d}) (moment matching's lag-one covariance, :func:`lag_inside_probability`); it is the product
  where consecutive states are uncorrelated and min-like where they are perfectly correlated;
- the constrained return V = Σ_t S_t (E[r(x_t)] − c_t), with the penalty cost c_t = Σ_k w_k (1 − p_{k,t}) over
  the penalty constraints (without terminate constraints S_t = 1: V = Σ_t (E[r(x_t)] − c_t)).

Particles take the same formulas per particle with a relaxed indicator in place of p_{k,t}: the logistic
sigmoid of the signed distance to each bound over a temperature τ (state units),
σ((x_d − l)/τ) σ((h − x_d)/τ); τ = 0 is the hard indicator (no gradient), and the survival is the running
product of the relaxed indicators, averaged over the particles.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from qtl.gaussian import Gaussian

CONSTRAINT_KINDS = ("terminate", "penalty")  # task.constraints[i].kind
SURVIVALS = ("markov", "product")  # propagation.survival: moment matching's survival over steps (see above)
# Gauss–Legendre nodes of the bivariate normal CDF's integral over θ = asin r (Plackett's identity): its integrand is
# smooth in θ; 48 nodes give ~1e-10 against scipy's Genz algorithm for |ρ| <= 0.9999 (tests/test_constraints.py).
BIVARIATE_NODES = 48
# Standardised bounds are clipped to ±this: Φ(±BOUND_CLIP) is 0 or 1 to double precision.
BOUND_CLIP = 40.0
# The particles' relaxed indicator: the sigmoid's temperature τ in state units (the bound's soft width ~ 4τ).
PARTICLE_TEMPERATURE = 1e-2
# The survival below which a step counts as "the prediction more likely ended than not" (survival_half_step).
HALF_SURVIVAL = 0.5
SQRT_HALF = math.sqrt(0.5)


@dataclass(frozen=True)
class Constraint:
    """Bounds [``low``, ``high``] on state dimension ``dim`` (None: unbounded there); ``kind`` terminate or penalty.

    ``weight``: the cost of a step outside the bounds (penalty only; 0 for terminate).
    """

    dim: int
    low: float | None = None
    high: float | None = None
    kind: str = "terminate"
    weight: float = 0.0

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> Constraint:
        """One ``task.constraints`` entry, checked by ``qtl.config.validate.checked_task`` (not here)."""
        low, high = cfg.get("low"), cfg.get("high")
        return cls(dim=int(cfg["dim"]), low=None if low is None else float(low),
                   high=None if high is None else float(high), kind=str(cfg.get("kind", "terminate")),
                   weight=float(cfg.get("weight") or 0.0))

    def contains(self, states: np.ndarray) -> np.ndarray:
        """Whether each state `... x D` is within the bounds: `...` (bool)."""
        x = np.asarray(states, dtype=float)[..., self.dim]
        inside = np.ones(x.shape, dtype=bool)
        if self.low is not None:
            inside &= x >= self.low
        if self.high is not None:
            inside &= x <= self.high
        return inside


def terminating(constraints: Sequence[Constraint]) -> tuple[Constraint, ...]:
    """The constraints of kind ``terminate``."""
    return tuple(c for c in constraints if c.kind == "terminate")


def penalties(constraints: Sequence[Constraint]) -> tuple[Constraint, ...]:
    """The constraints of kind ``penalty``."""
    return tuple(c for c in constraints if c.kind == "penalty")


def inside_probability(constraint: Constraint, mean: Tensor, var: Tensor) -> Tensor:
    """p = P(l ≤ x_d ≤ h) under x_d ~ N(``mean[..., d]``, ``var[..., d]``): `...` for mean and var `... x D`.

    Φ(b) − Φ(a) with a, b the standardised bounds; both in the upper tail, Φ(−a) − Φ(−b) (the same, without
    the cancellation). Differentiable in mean and var.
    """
    mu = mean[..., constraint.dim]
    sigma = var[..., constraint.dim].clamp_min(torch.finfo(var.dtype).tiny).sqrt()
    a = (constraint.low - mu) / sigma if constraint.low is not None else torch.full_like(mu, -math.inf)
    b = (constraint.high - mu) / sigma if constraint.high is not None else torch.full_like(mu, math.inf)
    return torch.where(a > 0, _ndtr(-a) - _ndtr(-b), _ndtr(b) - _ndtr(a))


def _ndtr(z: Tensor) -> Tensor:
    """Φ(z) = ½ erfc(−z/√2) `...`: accurate far in the lower tail (torch.special.ndtr flushes Φ(−9) to 0)."""
    return 0.5 * torch.special.erfc(-z * SQRT_HALF)


def bivariate_normal_cdf(h: Tensor, k: Tensor, rho: Tensor) -> Tensor:
    """Φ₂(h, k; ρ) = P(X ≤ h, Y ≤ k) of standard normals of correlation ρ ∈ (−1, 1), all `...`, differentiable.

    Plackett's identity ∂Φ₂/∂ρ = φ₂ integrated from ρ = 0, with r = sin θ: Φ₂ = Φ(h)Φ(k) +
    (1/2π) ∫_0^{asin ρ} exp(−(h² − 2hk sin θ + k²) / (2 cos² θ)) dθ, a smooth integrand (Gauss–Legendre).
    """
    nodes, weights = _legendre(BIVARIATE_NODES, h.dtype, h.device)
    h, k, rho = (t.clamp(-BOUND_CLIP, BOUND_CLIP) for t in torch.broadcast_tensors(h, k, rho))
    end = torch.asin(rho)[..., None]  # ... x 1
    theta = 0.5 * end * (nodes + 1)  # ... x N, on [0, asin ρ] (or [asin ρ, 0])
    sin, cos_sq = torch.sin(theta), torch.cos(theta).square()
    hh, kk = h[..., None], k[..., None]
    integrand = torch.exp(-(hh.square() - 2 * hh * kk * sin + kk.square()) / (2 * cos_sq))
    return _ndtr(h) * _ndtr(k) + 0.5 * end[..., 0] * (integrand * weights).sum(-1) / (2 * math.pi)


def _legendre(count: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """Gauss–Legendre nodes and weights on [−1, 1]: `count` each."""
    nodes, weights = np.polynomial.legendre.leggauss(count)
    return (torch.as_tensor(nodes, dtype=dtype, device=device), torch.as_tensor(weights, dtype=dtype, device=device))


def _standardised(constraint: Constraint, mu: Tensor, sigma: Tensor) -> tuple[Tensor, Tensor]:
    """The bounds (l − μ)/σ and (h − μ)/σ `...`, ∓BOUND_CLIP where unbounded."""
    low = (constraint.low - mu) / sigma if constraint.low is not None else torch.full_like(mu, -BOUND_CLIP)
    high = (constraint.high - mu) / sigma if constraint.high is not None else torch.full_like(mu, BOUND_CLIP)
    return low.clamp(-BOUND_CLIP, BOUND_CLIP), high.clamp(-BOUND_CLIP, BOUND_CLIP)


def lag_inside_probability(constraint: Constraint, before: Gaussian, after: Gaussian, lag_cov: Tensor) -> Tensor:
    """P(x_{t−1} and x_t inside) `...` from their marginals ``before``, ``after`` and cov(x_{t−1}, x_t) `... x D x D`.

    The rectangle probability of the bivariate Gaussian of (x_{t−1,d}, x_{t,d}): four corners of Φ₂.
    """
    d = constraint.dim
    tiny = torch.finfo(lag_cov.dtype).tiny
    sd0 = before.cov[..., d, d].clamp_min(tiny).sqrt()
    sd1 = after.cov[..., d, d].clamp_min(tiny).sqrt()
    limit = 1 - 1e-12
    rho = (lag_cov[..., d, d] / (sd0 * sd1)).clamp(-limit, limit)
    a0, b0 = _standardised(constraint, before.mean[..., d], sd0)
    a1, b1 = _standardised(constraint, after.mean[..., d], sd1)
    corners = bivariate_normal_cdf(torch.stack([b0, a0, b0, a0]), torch.stack([b1, b1, a1, a1]),
                                   rho.expand(4, *rho.shape))
    return (corners[0] - corners[1] - corners[2] + corners[3]).clamp(0.0, 1.0)


def soft_inside(constraint: Constraint, x: Tensor, temperature: float = PARTICLE_TEMPERATURE) -> Tensor:
    """σ((x_d − l)/τ) σ((h − x_d)/τ) of particles ``x`` `... x D`: `...`; τ = 0: the hard indicator 1[l ≤ x_d ≤ h]."""
    xd = x[..., constraint.dim]
    inside = torch.ones_like(xd)
    for side in ((xd - constraint.low) if constraint.low is not None else None,
                 (constraint.high - xd) if constraint.high is not None else None):
        if side is not None:
            inside = inside * (torch.sigmoid(side / temperature) if temperature > 0 else (side >= 0).to(xd))
    return inside


def constrained_return(
    constraints: Sequence[Constraint], rewards: Tensor, inside: Callable[[Constraint], Tensor],
    staying: Callable[[Constraint], Tensor] | None = None,
) -> tuple[Tensor, Tensor | None]:
    """V = Σ_t S_t (r_t − c_t) `...` and the survival S_t `... x H` (None without terminate constraints).

    ``rewards`` r_t `... x H`; ``inside(c)`` `... x H` the probability (or relaxed indicator) that x_t is within
    constraint c. S_t = Π_{τ≤t} Π_k q_{k,τ} over the terminate constraints (the product over them), q = ``staying(c)``
    (the probability of staying inside at each step given the last, `... x H`; default ``inside``: the product
    survival); c_t = Σ_k w_k (1 − p_{k,t}) over the penalty constraints.
    """
    step = rewards
    for c in penalties(constraints):
        step = step - c.weight * (1.0 - inside(c))
    survival = None
    stops = terminating(constraints)
    staying = inside if staying is None else staying
    if stops:
        p = staying(stops[0])
        for c in stops[1:]:
            p = p * staying(c)
        survival = torch.cumprod(p, dim=-1)
        step = survival * step
    return step.sum(-1), survival


def gaussian_return(
    constraints: Sequence[Constraint], rewards: Tensor, states: Gaussian, lag_cov: Tensor | None = None
) -> tuple[Tensor, Tensor | None]:
    """:func:`constrained_return` of Gaussian states x_1..x_H (mean `... x H x D`, cov `... x H x D x D`).

    ``lag_cov``: cov(x_{t−1}, x_t) `... x H x D x D` for t = 1..H: the ``markov`` survival (see the module); None: the
    ``product`` survival.
    """
    var = torch.diagonal(states.cov, dim1=-2, dim2=-1)
    marginal = functools.partial(_marginal_inside, mean=states.mean, var=var)
    if lag_cov is None or not terminating(constraints):
        return constrained_return(constraints, rewards, marginal)
    return constrained_return(constraints, rewards, marginal,
                              functools.partial(_markov_step, states=states, lag_cov=lag_cov, marginal=marginal))


def _marginal_inside(constraint: Constraint, mean: Tensor, var: Tensor) -> Tensor:
    """p_t of ``constraint`` from the marginals (mean, var `... x H x D`): `... x H`."""
    return inside_probability(constraint, mean, var)


def _markov_step(constraint: Constraint, states: Gaussian, lag_cov: Tensor, marginal: Callable[[Constraint], Tensor]
                 ) -> Tensor:
    """q_t of ``constraint``: p_1, then P(x_{t−1}, x_t inside) / P(x_{t−1} inside) for t = 2..H: `... x H`."""
    p = marginal(constraint)  # ... x H
    before = Gaussian(states.mean[..., :-1, :], states.cov[..., :-1, :, :])
    after = Gaussian(states.mean[..., 1:, :], states.cov[..., 1:, :, :])
    both = lag_inside_probability(constraint, before, after, lag_cov[..., 1:, :, :])  # ... x H−1
    ratio = (both / p[..., :-1].clamp_min(torch.finfo(p.dtype).tiny)).clamp(max=1.0)
    return torch.cat([p[..., :1], ratio], dim=-1)


def particle_return(
    constraints: Sequence[Constraint], rewards: Tensor, states: Tensor, temperature: float = PARTICLE_TEMPERATURE
) -> tuple[Tensor, Tensor | None]:
    """:func:`constrained_return` per particle: rewards `... x P x H`, states x_1..x_H `... x P x H x D`.

    V `... x P` and S `... x P x H` per particle, with the relaxed indicator of temperature τ.
    """
    return constrained_return(constraints, rewards, lambda c: soft_inside(c, states, temperature))


def half_survival_step(survival: Tensor | None) -> int | None:
    """The first step t (1..H) whose S_t < 0.5, of a survival `H`; None when it never falls below."""
    if survival is None:
        return None
    if survival.dim() != 1:
        raise ValueError(f"the survival of one rollout is `H`, got shape {tuple(survival.shape)}")
    below = (survival.detach() < HALF_SURVIVAL).nonzero()
    return int(below[0, 0]) + 1 if len(below) else None


def crossed(constraints: Sequence[Constraint], states: np.ndarray) -> bool:
    """Whether any of the states `T+1 x D` of a real episode left the bounds of any constraint (either kind)."""
    return any(not c.contains(states).all() for c in constraints)
