"""Sine squashing of actions to [−u_max, u_max]: u = u_max (9 sin z + sin 3z)/8 (PILCO gSat)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from qtl.features import trig_moments
from qtl.gaussian import Gaussian, GaussianMap, MomentMatch, compose, symmetrize
from qtl.policies.base import Policy

# u = u_max (SIN_WEIGHT sin z + SIN3_WEIGHT sin(SIN3_FREQ z)): the third-order Fourier
# truncation of a hard clip, monotone on [−π/2, π/2] with |u| <= u_max everywhere.
SIN_WEIGHT = 9.0 / 8.0
SIN3_WEIGHT = 1.0 / 8.0
SIN3_FREQ = 3.0


def sin_squash(z: Tensor, bound: Tensor) -> Tensor:
    """u = u_max (9 sin z + sin 3z)/8 elementwise, ``z`` `... x F`, ``bound`` `F` (u_max)."""
    return bound * (SIN_WEIGHT * z.sin() + SIN3_WEIGHT * (SIN3_FREQ * z).sin())


def sin_squash_moments(state: Gaussian, bound: Tensor) -> MomentMatch:
    """Exact mean, covariance and input–output terms of :func:`sin_squash` for z ~ N(μ, Σ)."""
    state = state.expand()
    num = state.dim
    eye = torch.eye(num, dtype=state.dtype, device=state.mean.device)
    lift = torch.cat([eye, SIN3_FREQ * eye], dim=0)  # φ = A z = [z, 3z]: 2F x F
    phi_mean = state.mean @ lift.mT
    phi_cov = lift @ state.cov @ lift.mT
    trig_mean, trig_cov, trig_gain = trig_moments(phi_mean, phi_cov)
    sines = slice(0, None, 2)  # trig_moments interleaves (sin, cos) per angle
    # u = L sin φ with L = [9/8 diag(u_max), 1/8 diag(u_max)].
    mix = torch.cat([SIN_WEIGHT * torch.diag(bound), SIN3_WEIGHT * torch.diag(bound)], dim=-1).to(phi_mean)
    mean = trig_mean[..., sines] @ mix.mT
    cov = mix @ trig_cov[..., sines, sines] @ mix.mT
    # Stein's lemma through the linear lift: E[∂u/∂z]ᵀ = Aᵀ E[∂ sin φ/∂φ]ᵀ Lᵀ.
    gain = lift.mT @ trig_gain[..., sines] @ mix.mT
    return MomentMatch(mean=mean, cov=symmetrize(cov), cross_cov=state.cov @ gain, gain=gain)


class SquashedPolicy(Policy):
    """u = u_max (9 sin z + sin 3z)/8 with z = policy(y); ψ is the wrapped policy's."""

    def __init__(self, policy: Policy, action_bound: float | Sequence[float] | Tensor) -> None:
        super().__init__()
        self.policy = policy
        self.input_dim, self.output_dim = policy.input_dim, policy.output_dim
        bound = torch.as_tensor(action_bound, dtype=torch.float64).flatten()
        if bound.numel() == 1:
            bound = bound.expand(self.output_dim).clone()
        if bound.shape != (self.output_dim,) or (bound <= 0).any():
            raise ValueError(f"action_bound must be positive, one per action ({self.output_dim})")
        self.register_buffer("action_bound", bound)

    def forward(self, x: Tensor) -> Tensor:
        """Squashed actions `... x F` for features `... x D`."""
        return sin_squash(self.policy(x), self.action_bound.to(x))

    def prepare(self) -> GaussianMap:
        """The wrapped policy's moments, then exact squashing moments, chained (PILCO conCat)."""
        inner = self.policy.prepare()

        def moments(state: Gaussian) -> MomentMatch:
            pre = inner(state)
            return compose(pre, sin_squash_moments(pre.output, self.action_bound.to(pre.mean)))

        return moments
