"""Initial policies for a task, built at run time from the configured group option (``policy/``)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from qtl.features import AngleFeatures
from qtl.policies.linear import LinearPolicy
from qtl.policies.rbf import INIT_TARGET_STD, RBFPolicy
from qtl.policies.rbf_network import RBFNetwork


def rbf_policy(
    input_dim: int,
    output_dim: int,
    *,
    num_basis: int,
    start_features: Tensor,
    features: AngleFeatures | None = None,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
) -> RBFPolicy:
    """PILCO's initial RBF policy: support points drawn around the start, small random targets.

    ``start_features``: `S x D` features of draws from the start distribution, S >= ``num_basis``;
    ``features`` (the state-to-feature map) is not needed here.
    """
    if start_features.shape[0] < num_basis or start_features.shape[-1] != input_dim:
        raise ValueError(
            f"start_features must be `S x {input_dim}` with S >= {num_basis}, got {tuple(start_features.shape)}"
        )
    targets = INIT_TARGET_STD * torch.randn(num_basis, output_dim, generator=generator, dtype=dtype)
    return RBFPolicy(
        input_dim, output_dim, num_basis, support_points=start_features[:num_basis].to(dtype), targets=targets,
        dtype=dtype,
    )


def linear_policy(
    input_dim: int,
    output_dim: int,
    *,
    start_features: Tensor,
    features: AngleFeatures | None = None,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
) -> LinearPolicy:
    """A small random linear policy centred on the start: u = W (y − ȳ_0) at first (``features`` not needed)."""
    policy = LinearPolicy(input_dim, output_dim, generator=generator, dtype=dtype)
    with torch.no_grad():
        policy.bias.copy_(-(policy.weight @ start_features.to(dtype).mean(0)))
    return policy


def rbf_network_policy(
    input_dim: int,
    output_dim: int,
    *,
    num_basis: int,
    start_features: Tensor,
    features: AngleFeatures | None = None,
    centre_range: float = math.pi,
    weight_range: float = 0.5,
    lengthscale: float = 1 / math.sqrt(2),
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
) -> RBFNetwork:
    """MC-PILCO's initial sum of Gaussians: centres spread uniformly over the state space, uniform random weights.

    Centres are the features of states drawn with every non-angle dimension uniform in
    ±``centre_range`` and every angle uniform in [−π, π) (``features``: the state-to-feature map;
    without it, every feature is uniform in ±``centre_range``); weights uniform in ±``weight_range``;
    every length-scale ``lengthscale`` (MC-PILCO's 1 in its exp(−d²) form). ``start_features`` is not needed here.
    """
    if centre_range <= 0 or weight_range < 0 or lengthscale <= 0:
        raise ValueError(f"centre_range and lengthscale must be > 0 and weight_range >= 0, got "
                         f"{centre_range}, {lengthscale} and {weight_range}")
    del start_features
    if features is None:
        centres = centre_range * (2 * torch.rand(num_basis, input_dim, generator=generator, dtype=dtype) - 1)
    else:
        if features.output_dim != input_dim:
            raise ValueError(f"features give {features.output_dim}-D features, the policy takes {input_dim}")
        states = centre_range * (2 * torch.rand(num_basis, features.state_dim, generator=generator, dtype=dtype) - 1)
        angles = list(features.angle_dims)
        if angles:
            states[:, angles] *= math.pi / centre_range
        centres = features(states)
    weights = weight_range * (2 * torch.rand(num_basis, output_dim, generator=generator, dtype=dtype) - 1)
    lengthscales = torch.full((output_dim, input_dim), lengthscale, dtype=dtype)
    return RBFNetwork(centres, weights, lengthscales)
