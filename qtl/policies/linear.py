"""The linear policy u = W y + b, with exact moments under a Gaussian input."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from qtl.gaussian import Gaussian, GaussianMap, MomentMatch
from qtl.kernels.engine import DEFAULT_ENGINE, Engine
from qtl.policies.base import Policy

# Standard deviation of the random initial entries of W.
INIT_WEIGHT_STD = 0.1


class LinearPolicy(Policy):
    """u = W y + b; ψ = (``weight`` `F x D`, ``bias`` `F`)."""

    def __init__(
        self,
        input_dim: int,
        output_dim: int,
        *,
        weight: Tensor | None = None,
        bias: Tensor | None = None,
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        self.input_dim, self.output_dim = input_dim, output_dim
        if weight is None:
            weight = INIT_WEIGHT_STD * torch.randn(output_dim, input_dim, generator=generator, dtype=dtype)
        if bias is None:
            bias = torch.zeros(output_dim, dtype=dtype)
        if weight.shape != (output_dim, input_dim) or bias.shape != (output_dim,):
            raise ValueError(
                f"weight must be `{output_dim} x {input_dim}` and bias `{output_dim}`, got "
                f"{tuple(weight.shape)} and {tuple(bias.shape)}"
            )
        self.weight = nn.Parameter(weight.to(dtype).clone())
        self.bias = nn.Parameter(bias.to(dtype).clone())

    def forward(self, x: Tensor) -> Tensor:
        """Actions `... x F` for features `... x D`; batched ψ: `R x S x F` for `R x S x D`."""
        if not self.batch_shape:
            return x @ self.weight.mT + self.bias
        return _row_times(x, self.per_point(self.weight)) + self.per_point(self.bias)

    def prepare(self, engine: Engine = DEFAULT_ENGINE) -> GaussianMap:
        """Exact moments: mean W μ + b, covariance W Σ Wᵀ, gain Wᵀ; batched ψ broadcast (every ``engine`` alike)."""
        weight, bias = self.weight, self.bias
        batched = bool(self.batch_shape)

        def moments(state: Gaussian) -> MomentMatch:
            state = state.expand()
            cross_cov = state.cov @ weight.mT  # ... x D x F
            return MomentMatch(
                mean=(_row_times(state.mean, weight) if batched else state.mean @ weight.mT) + bias,
                cov=weight @ cross_cov,
                cross_cov=cross_cov,
                gain=weight.mT.expand(*cross_cov.shape),
            )

        return moments


def _row_times(rows: Tensor, weight: Tensor) -> Tensor:
    """W r per row: `... x F` for rows `... x D` and W `... x F x D`, batch dimensions broadcast."""
    return (rows[..., None, :] @ weight.mT).squeeze(-2)
