"""An RBF network with free weights (MC-PILCO's sum of Gaussians), with exact moments and basis dropout."""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch
from torch import Tensor, nn
from torch.autograd.function import FunctionCtx, once_differentiable

from qtl.gaussian import GaussianMap
from qtl.kernels import SEKernelMoments
from qtl.kernels.engine import DEFAULT_ENGINE, Engine
from qtl.kernels.native import rbf_network as native_network
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

    def forward(self, x: Tensor, engine: Engine = DEFAULT_ENGINE) -> Tensor:
        """Actions `... x F` for features `... x D`, basis dropout applied when set.

        Unbatched ψ, points `... x D` (at least 2-D) and ``engine`` fused: one autograd op (``_NetworkValues``,
        the same values and gradients to round-off); native, for float64 CPU operands: its compiled twin
        (`qtl/kernels/native/rbf_network.c`); ``engine.network`` may pin one form (:class:`~qtl.kernels.Engine`).
        Their timings against this plain form: `scripts/bench_particle_step.py`.
        """
        keep = None
        if self.dropout > 0.0:  # one mask per point and basis, shared by the action dimensions
            keep = torch.rand((*x.shape[:-1], 1, self.num_basis), generator=self._dropout_generator,
                              dtype=x.dtype, device="cpu").to(x.device) >= self.dropout
        if engine.network != "reference" and engine.fused and not self.batch_shape and x.dim() >= 2:
            mask = None if keep is None else keep.to(x.dtype).div_(1.0 - self.dropout).reshape(-1, self.num_basis)
            points = x.reshape(-1, x.shape[-1])
            psi = (self.centres, self.weights, self.log_lengthscales)
            if engine.network == "auto" and engine.native and native_network.applicable(points, *psi, mask):
                values = native_network.network_values(points, *psi, mask)
            else:
                values = _NetworkValues.apply(points, *psi, mask)
            return values.reshape(*x.shape[:-1], self.output_dim)
        kern = self.activations(x)
        if keep is not None:
            kern = kern * keep / (1.0 - self.dropout)
        return (kern * self.per_point(self.weights.mT)).sum(-1)

    def actions(self, engine: Engine = DEFAULT_ENGINE) -> Callable[[Tensor], Tensor]:
        """``forward`` by ``engine`` (a particle rollout takes it once, calls it each step)."""
        return functools.partial(self.forward, engine=engine)

    def prepare(self, engine: Engine = DEFAULT_ENGINE) -> GaussianMap:
        """Exact moments of the network at Gaussian inputs (PILCO gp2; dropout does not apply); batched ψ broadcast."""
        signal = torch.ones(self.output_dim, dtype=self.weights.dtype, device=self.weights.device)
        return SEKernelMoments(self.centres, self.weights.mT, self.lengthscales, signal, engine=engine)


class _NetworkValues(torch.autograd.Function):
    """π̃(x) `M x F` for points x `M x D`, centres c `N x D`, weights w `N x F`, log ℓ `F x D`, mask `M x N` or None.

    The fused form of ``RBFNetwork.forward`` (unbatched ψ): ‖(x − c)/ℓ‖² expanded as one batched product over
    the action dimensions, and a closed-form backward from the kept activations k `F x M x N` (the mask, with
    its 1/(1 − p), folded in): with h = g w k, ∂x = −Σ_f ℓ_f⁻² (x Σ_s h − h c), ∂c = Σ_f ℓ_f⁻² (hᵀx − c Σ_p h),
    ∂w = Σ_p g k and ∂log ℓ = ℓ⁻² Σ_ps h (x − c)², the last expanded like the distance.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: FunctionCtx, x: Tensor, centres: Tensor, weights: Tensor, log_lengthscales: Tensor, mask: Tensor | None
    ) -> Tensor:
        inv_sq = torch.exp(-2.0 * log_lengthscales)  # ℓ⁻²: F x D
        scaled_x = x * inv_sq[:, None, :]  # F x M x D
        sq_dist = (scaled_x * x).sum(-1)[..., None] + (centres.square() @ inv_sq.mT).mT[:, None, :]
        sq_dist = sq_dist - 2.0 * (scaled_x @ centres.mT)  # F x M x N
        kern = torch.exp(sq_dist.clamp_min_(0.0).mul_(-0.5))
        if mask is not None:
            kern = kern.mul_(mask)
        ctx.save_for_backward(x, centres, weights, inv_sq, kern)
        return (kern @ weights.mT[..., None]).squeeze(-1).mT

    @staticmethod
    @once_differentiable
    def backward(ctx: FunctionCtx, grad_out: Tensor) -> tuple[Tensor | None, ...]:  # type: ignore[override]
        x, centres, weights, inv_sq, kern = ctx.saved_tensors
        need_x, need_c, need_w, need_ls = ctx.needs_input_grad[:4]
        grad_t = grad_out.mT  # F x M
        grad_w = (grad_t[:, None, :] @ kern).squeeze(-2).mT if need_w else None  # N x F
        h = kern * (grad_t[:, :, None] * weights.mT[:, None, :])  # F x M x N
        per_point, per_basis = h.sum(-1), h.sum(-2)  # F x M, F x N
        h_x = h.mT @ x if (need_c or need_ls) else None  # F x N x D
        grad_x = grad_c = grad_ls = None
        if need_x:
            grad_x = -(inv_sq[:, None, :] * (x * per_point[..., None] - h @ centres)).sum(0)
        if need_c:
            grad_c = (inv_sq[:, None, :] * (h_x - centres * per_basis[..., None])).sum(0)
        if need_ls:
            grad_ls = inv_sq * (per_point @ x.square() - 2.0 * (h_x * centres).sum(-2) + per_basis @ centres.square())
        return grad_x, grad_c, grad_w, grad_ls, None
