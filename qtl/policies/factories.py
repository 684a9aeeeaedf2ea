"""Initial policies for a task, built at run time from the configured group option (``policy/``)."""

from __future__ import annotations

import torch
from torch import Tensor

from qtl.policies.linear import LinearPolicy
from qtl.policies.rbf import INIT_TARGET_STD, RBFPolicy


def rbf_policy(
    input_dim: int,
    output_dim: int,
    *,
    num_basis: int,
    start_features: Tensor,
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
) -> RBFPolicy:
    """PILCO's initial RBF policy: support points drawn around the start, small random targets.

    ``start_features``: `S x D` features of draws from the start distribution, S >= ``num_basis``.
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
    generator: torch.Generator | None = None,
    dtype: torch.dtype = torch.float64,
) -> LinearPolicy:
    """A small random linear policy centred on the start: u = W (y − ȳ_0) at first."""
    policy = LinearPolicy(input_dim, output_dim, generator=generator, dtype=dtype)
    with torch.no_grad():
        policy.bias.copy_(-(policy.weight @ start_features.to(dtype).mean(0)))
    return policy
