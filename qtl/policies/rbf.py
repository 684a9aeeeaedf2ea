"""The RBF-network policy of Eq. 5, a deterministic GP mean, with exact moments (PILCO gp2)."""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch
from torch import Tensor, nn

from qtl.gaussian import GaussianMap, cholesky, nan_where
from qtl.kernels import SEKernelMoments
from qtl.kernels.engine import DEFAULT_ENGINE, Engine
from qtl.policies.base import Policy

# The policy's pseudo-GP has fixed hyper-parameters (PILCO): signal variance 1 and noise
# variance σ_π² = 0.01, which regularises the weights β_π = (K_π + σ_π²I)⁻¹ y_π.
POLICY_SIGNAL_VARIANCE = 1.0
POLICY_NOISE_VARIANCE = 0.01
# Default random initialisation: support points ~ N(0, I), targets ~ N(0, 0.1²), ℓ = 1.
INIT_TARGET_STD = 0.1
INIT_LENGTHSCALE = 1.0


def se_activations(policy: Policy, x: Tensor, centres: Tensor) -> Tensor:
    """exp(−½ ‖(y − c_s)/ℓ‖²) `... x F x N` for features ``x`` `... x D` (batched ψ: `R x S x D`).

    ``centres`` c `(R x) N x D`; the length-scales are ``policy.log_lengthscales`` `(R x) F x D`.
    ‖(y − c)/ℓ‖² is expanded, so that memory is `... x F x N` rather than `... x F x N x D`; with one
    action the cross term is one matrix product (per restart), not a matrix-vector product per point.
    """
    inv_ls = policy.log_lengthscales.neg().exp()  # (R x) F x D
    scaled_c = centres[..., None, :, :] * inv_ls[..., :, None, :]  # (R x) F x N x D
    scaled_x = x[..., None, :] * policy.per_point(inv_ls)  # ... x F x D
    if policy.output_dim == 1 and x.dim() >= 2:
        cross = (scaled_x[..., 0, :] @ scaled_c[..., 0, :, :].mT)[..., None, :]  # ... x 1 x N
    else:
        cross = (scaled_x[..., :, None, :] @ policy.per_point(scaled_c).mT).squeeze(-2)  # ... x F x N
    sq_dist = scaled_x.square().sum(-1)[..., None] + policy.per_point(scaled_c.square().sum(-1)) - 2 * cross
    return torch.exp(-0.5 * sq_dist.clamp_min(0.0))


class RBFPolicy(Policy):
    """π̃(y) = Σ_s β_s k_π(x_s, y) (Eq. 5) with β_π = (K_π + σ_π²I)⁻¹ y_π per action dimension.

    ψ = (``support_points`` X_π `N x D`, ``targets`` y_π `N x F`, ``log_lengthscales``
    `F x D`); k_π is the SE kernel of Eq. 3 with signal variance 1.
    """

    def __init__(
        self,
        input_dim: int,
        output_dim: int,
        num_basis: int,
        *,
        support_points: Tensor | None = None,
        targets: Tensor | None = None,
        lengthscales: Tensor | None = None,
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        self.input_dim, self.output_dim, self.num_basis = input_dim, output_dim, num_basis
        if support_points is None:
            support_points = torch.randn(num_basis, input_dim, generator=generator, dtype=dtype)
        if targets is None:
            targets = INIT_TARGET_STD * torch.randn(num_basis, output_dim, generator=generator, dtype=dtype)
        if lengthscales is None:
            lengthscales = torch.full((output_dim, input_dim), INIT_LENGTHSCALE, dtype=dtype)
        expected = {
            "support_points": (support_points, (num_basis, input_dim)),
            "targets": (targets, (num_basis, output_dim)),
            "lengthscales": (lengthscales, (output_dim, input_dim)),
        }
        for name, (value, shape) in expected.items():
            if tuple(value.shape) != shape:
                raise ValueError(f"{name} must have shape {shape}, got {tuple(value.shape)}")
        if (lengthscales <= 0).any():
            raise ValueError("lengthscales must be positive")
        self.support_points = nn.Parameter(support_points.to(dtype).clone())
        self.targets = nn.Parameter(targets.to(dtype).clone())
        self.log_lengthscales = nn.Parameter(lengthscales.to(dtype).log())

    @property
    def lengthscales(self) -> Tensor:
        """ℓ `F x D`."""
        return self.log_lengthscales.exp()

    def _signal_variance(self) -> Tensor:
        """α² = 1 for every action dimension: `F`."""
        return torch.full(
            (self.output_dim,), POLICY_SIGNAL_VARIANCE, dtype=self.targets.dtype, device=self.targets.device
        )

    def weights(self) -> Tensor:
        """β_π = (K_π + σ_π²I)⁻¹ y_π per action dimension (Eq. 5): `... x F x N` (`...`: ``batch_shape``)."""
        scaled = self.support_points[..., None, :, :] / self.lengthscales[..., :, None, :]  # ... x F x N x D
        sq_dist = (scaled[..., :, None, :] - scaled[..., None, :, :]).square().sum(-1)
        gram = POLICY_SIGNAL_VARIANCE * torch.exp(-0.5 * sq_dist)
        gram = gram + POLICY_NOISE_VARIANCE * torch.eye(self.num_basis, dtype=gram.dtype, device=gram.device)
        chol, failed = cholesky(gram)  # not positive-definite: raises, or NaN (qtl.gaussian.element_failures)
        return nan_where(failed, torch.cholesky_solve(self.targets.mT[..., None], chol).squeeze(-1))

    def forward(self, x: Tensor) -> Tensor:
        """Actions `... x F` for features `... x D` (Eq. 5); batched ψ: `R x S x F` for `R x S x D`."""
        return self._act(x, self.per_point(self.weights()))

    def actions(self, engine: Engine = DEFAULT_ENGINE) -> Callable[[Tensor], Tensor]:
        """``forward`` with β_π = (K_π + σ_π²I)⁻¹ y_π solved once (not at every step of a rollout)."""
        return functools.partial(self._act, weights=self.per_point(self.weights()))

    def _act(self, x: Tensor, weights: Tensor) -> Tensor:
        """Σ_s β_s k_π(x_s, y) for features ``x`` and per-point β_π ``weights``."""
        kern = POLICY_SIGNAL_VARIANCE * se_activations(self, x, self.support_points)
        return (kern * weights).sum(-1)

    def prepare(self, engine: Engine = DEFAULT_ENGINE) -> GaussianMap:
        """Exact moments of the RBF network at Gaussian inputs, β_π computed once (PILCO gp2); batched ψ broadcast."""
        return SEKernelMoments(self.support_points, self.weights(), self.lengthscales, self._signal_variance(),
                               engine=engine)
