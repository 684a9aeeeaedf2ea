"""An RBF network with free weights (MC-PILCO's sum of Gaussians), with exact moments and basis dropout."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from qtl.gaussian import GaussianMap
from qtl.kernels import SEKernelMoments
from qtl.policies.base import Policy
from qtl.policies.rbf import se_activations


class RBFNetwork(Policy):
    """π̃(y) = Σ_s w_s exp(−½ ‖(y − c_s)/ℓ‖²) per action dimension: Eq. 5 with the weights as parameters.

    ψ = (``centres`` c `N x D`, ``weights`` w `N x F`, ``log_lengthscales`` `F x D`). Unlike
    :class:`~qtl.policies.RBFPolicy` (PILCO's pseudo-GP, β = (K + σ_π²I)⁻¹ y) there is no Gram solve,
    so N can be large (MC-PILCO uses 200). Moment matching sees the same network (PILCO gp2). With
    :meth:`set_dropout` each basis activation is dropped independently per point with probability p
    and the rest scaled by 1/(1 − p) in ``forward`` (MC-PILCO's policy dropout, for particle searches).
    """

    def __init__(self, centres: Tensor, weights: Tensor, lengthscales: Tensor) -> None:
        super().__init__()
        num_basis, input_dim = centres.shape
        output_dim = weights.shape[-1]
        if weights.shape != (num_basis, output_dim) or lengthscales.shape != (output_dim, input_dim):
            raise ValueError(
                f"centres `N x D`, weights `N x F` and lengthscales `F x D` must agree, got "
                f"{tuple(centres.shape)}, {tuple(weights.shape)} and {tuple(lengthscales.shape)}"
            )
        if (lengthscales <= 0).any():
            raise ValueError("lengthscales must be positive")
        self.input_dim, self.output_dim, self.num_basis = input_dim, output_dim, num_basis
        self.centres = nn.Parameter(centres.clone())
        self.weights = nn.Parameter(weights.to(centres).clone())
        self.log_lengthscales = nn.Parameter(lengthscales.to(centres).log())
        self.dropout = 0.0
        self._dropout_generator: torch.Generator | None = None

    @property
    def lengthscales(self) -> Tensor:
        """ℓ `F x D`."""
        return self.log_lengthscales.exp()

    def set_dropout(self, rate: float, generator: torch.Generator | None = None) -> None:
        """Drop each basis activation with probability ``rate`` in ``forward`` (0: off), masks from ``generator``."""
        if not 0.0 <= rate < 1.0:
            raise ValueError(f"dropout rate must be in [0, 1), got {rate}")
        self.dropout, self._dropout_generator = float(rate), generator

    def activations(self, x: Tensor) -> Tensor:
        """exp(−½ ‖(y − c_s)/ℓ‖²) `... x F x N` for features `... x D` (batched ψ: `R x S x D`)."""
        return se_activations(self, x, self.centres)

    def forward(self, x: Tensor) -> Tensor:
        """Actions `... x F` for features `... x D`, basis dropout applied when set."""
        kern = self.activations(x)
        if self.dropout > 0.0:  # one mask per point and basis, shared by the action dimensions
            keep = torch.rand((*kern.shape[:-2], 1, kern.shape[-1]), generator=self._dropout_generator,
                              dtype=kern.dtype, device="cpu").to(kern.device) >= self.dropout
            kern = kern * keep / (1.0 - self.dropout)
        return (kern * self.per_point(self.weights.mT)).sum(-1)

    def prepare(self) -> GaussianMap:
        """Exact moments of the network at Gaussian inputs (PILCO gp2; dropout does not apply); batched ψ broadcast."""
        signal = torch.ones(self.output_dim, dtype=self.weights.dtype, device=self.weights.device)
        return SEKernelMoments(self.centres, self.weights.mT, self.lengthscales, signal)
