"""Angle features: θ ↦ (sin θ, cos θ) on states and on Gaussian state distributions (PILCO's gTrig).

The convention is the project's one (``envs.rewards.augment_angles``): the augmented vector is
the non-angle dimensions in their order, then ``sin θ_a, cos θ_a`` for each ``a`` in
``angle_dims``; the raw angle is dropped.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from qtl.gaussian import Gaussian, MomentMatch, symmetrize


def _exp_times_expm1(log_scale: Tensor, s: Tensor) -> Tensor:
    """exp(log_scale) · (e^s − 1), accurate for small s and free of overflow for large |s|.

    Here |s| <= −log_scale (Cauchy–Schwarz: |σ_ij| <= (σ_i² + σ_j²)/2), so for s >= 0 the
    form exp(log_scale + s)(1 − e^{−s}) never overflows, where exp(log_scale)·expm1(s) would
    give inf · 0 once σ² passes ~700. Both branches are evaluated on clamped arguments, so
    neither produces inf and their gradients stay finite.
    """
    pos, neg = s.clamp_min(0.0), s.clamp_max(0.0)
    return torch.where(s >= 0, torch.exp(log_scale + pos) * -torch.expm1(-pos), torch.exp(log_scale) * torch.expm1(neg))


def trig_moments(mean: Tensor, cov: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Exact moments of (sin φ_1, cos φ_1, …, sin φ_K, cos φ_K) for φ ~ N(mean, cov).

    ``mean`` `... x K`, ``cov`` `... x K x K`. Returns the mean `... x 2K`, the covariance
    `... x 2K x 2K` and the expected Jacobian transposed `... x K x 2K` (Σ⁻¹ cov[φ, ·]).
    E[sin φ] = exp(−σ²/2) sin μ; the cross moments use E[cos(φ_i ± φ_j)], written with
    expm1 so that a vanishing covariance gives an exactly vanishing output covariance.
    """
    num = mean.shape[-1]
    var = torch.diagonal(cov, dim1=-2, dim2=-1)
    damp = torch.exp(-0.5 * var)
    e_sin, e_cos = damp * mean.sin(), damp * mean.cos()
    out_mean = torch.stack([e_sin, e_cos], dim=-1).flatten(-2)

    log_outer = -0.5 * (var[..., :, None] + var[..., None, :])  # log exp(−(σ_i² + σ_j²)/2)
    diff = mean[..., :, None] - mean[..., None, :]
    plus = mean[..., :, None] + mean[..., None, :]
    grow = _exp_times_expm1(log_outer, cov)  # exp(−(σ_i² + σ_j²)/2) (e^{σ_ij} − 1)
    shrink = _exp_times_expm1(log_outer, -cov)  # exp(−(σ_i² + σ_j²)/2) (e^{−σ_ij} − 1)
    ss = 0.5 * (grow * diff.cos() - shrink * plus.cos())
    cc = 0.5 * (grow * diff.cos() + shrink * plus.cos())
    sc = 0.5 * (shrink * plus.sin() + grow * diff.sin())  # cov[sin φ_i, cos φ_j]
    blocks = torch.stack([ss, sc, sc.mT, cc], dim=-1).unflatten(-1, (2, 2))  # ... K K 2 2
    out_cov = blocks.permute(*range(blocks.dim() - 4), -4, -2, -3, -1).reshape(*blocks.shape[:-4], 2 * num, 2 * num)

    eye = torch.eye(num, dtype=mean.dtype, device=mean.device)
    # d sin φ_k / dφ_k = cos φ_k, d cos φ_k / dφ_k = −sin φ_k.
    gain = torch.stack([eye * e_cos[..., None, :], -eye * e_sin[..., None, :]], dim=-1).flatten(-2)
    return out_mean, symmetrize(out_cov), gain


class AngleFeatures:
    """The map x ↦ y = [x_other, sin θ_a, cos θ_a, …] for a raw state of dimension ``state_dim``."""

    def __init__(self, state_dim: int, angle_dims: Sequence[int] = ()) -> None:
        angle_dims = tuple(int(a) for a in angle_dims)
        if any(not 0 <= a < state_dim for a in angle_dims):
            raise ValueError(f"angle_dims {angle_dims} out of range for state_dim {state_dim}")
        if len(set(angle_dims)) != len(angle_dims):
            raise ValueError(f"angle_dims {angle_dims} contain duplicates")
        self.state_dim = state_dim
        self.angle_dims = angle_dims
        self.other_dims = tuple(i for i in range(state_dim) if i not in set(angle_dims))

    @property
    def output_dim(self) -> int:
        """Dimension of the augmented vector: D + number of angles."""
        return self.state_dim + len(self.angle_dims)

    def __call__(self, x: Tensor) -> Tensor:
        """Augment raw states `... x D` to `... x (D + K)`."""
        if x.shape[-1] != self.state_dim:
            raise ValueError(f"expected states `... x {self.state_dim}`, got {tuple(x.shape)}")
        angles = x[..., list(self.angle_dims)]
        trig = torch.stack([angles.sin(), angles.cos()], dim=-1).flatten(-2)
        return torch.cat([x[..., list(self.other_dims)], trig], dim=-1)

    def moments(self, state: Gaussian) -> MomentMatch:
        """Exact mean, covariance and input–output covariance of y for x ~ N(μ, Σ) (PILCO gTrig)."""
        if state.dim != self.state_dim:
            raise ValueError(f"expected a {self.state_dim}-D state, got {state.dim}-D")
        state = state.expand()
        mean, cov = state.mean, state.cov
        other, angles = list(self.other_dims), list(self.angle_dims)
        eye = torch.eye(self.state_dim, dtype=mean.dtype, device=mean.device)
        if not angles:
            gain = eye.expand(*cov.shape)
            return MomentMatch(mean=mean, cov=cov, cross_cov=cov, gain=gain)

        trig_mean, trig_cov, trig_gain = trig_moments(mean[..., angles], cov[..., angles, :][..., angles])
        # Σ⁻¹ cov[x, y] = E[∂y/∂x]ᵀ: unit columns for the kept dims, the trig gain on the angle rows.
        gain = torch.cat([eye[:, other].expand(*trig_gain.shape[:-2], -1, -1), eye[:, angles] @ trig_gain], dim=-1)
        cross_cov = cov @ gain  # D x (D + K)
        other_trig = cross_cov[..., other, len(other) :]  # cov[x_other, trig]
        out_cov = torch.cat(
            [
                torch.cat([cov[..., other, :][..., other], other_trig], dim=-1),
                torch.cat([other_trig.mT, trig_cov], dim=-1),
            ],
            dim=-2,
        )
        out_mean = torch.cat([mean[..., other], trig_mean], dim=-1)
        return MomentMatch(mean=out_mean, cov=symmetrize(out_cov), cross_cov=cross_cov, gain=gain)
