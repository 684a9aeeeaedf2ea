"""GP predictive mean and latent variance at deterministic points, with an analytic gradient (Eq. 1-2).

Per output a, with the SE kernel of Eq. 3 on points and training inputs already divided by the
lengthscales ℓ_a: k_a(z) = α_a² exp(−½‖z − d_i‖²) over the training inputs d_i, the mean
m_a(z) = k_a(z) β_a and the latent variance v_a(z) = α_a² − k_a(z) (K_a + σ_ε²I)⁻¹ k_a(z)ᵀ.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.autograd.function import FunctionCtx, once_differentiable


def se_kernel_rows(z: Tensor, data: Tensor, data_sq: Tensor, signal_variance: Tensor) -> Tensor:
    """k(z, d_n) = α² exp(−½‖z − d_n‖²) `... x E x P x n` for points and data over ℓ (Eq. 3), no autograd graph kept.

    Formed in place from z dᵀ; ‖z − d‖² >= 0 up to round-off, so the exponent is clamped at 0.
    """
    log_kern = torch.matmul(z, data.mT)  # ... x E x P x n
    log_kern.sub_(0.5 * z.square().sum(-1, keepdim=True)).sub_(0.5 * data_sq[..., None, :])
    return log_kern.clamp_max_(0.0).add_(signal_variance.log()[..., None, None]).exp_()


class _GPPredictive(torch.autograd.Function):
    """m = k β and v = α² − k K⁻¹ kᵀ per output (Eq. 1-2); the gradient flows to ``z`` only.

    Each output's mean and variance depend on ``z`` only through that output's row, so the
    forward pass also forms their gradients w.r.t. ``z`` (`... x E x P x D`) and keeps only
    those: no `P x n` tensor outlives the call, and backward is two products.
    """

    @staticmethod
    def forward(  # type: ignore[override]
        ctx: FunctionCtx,
        z: Tensor,
        data: Tensor,
        data_sq: Tensor,
        beta: Tensor,
        K_inv: Tensor,
        signal_variance: Tensor,
    ) -> tuple[Tensor, Tensor]:
        kern = se_kernel_rows(z, data, data_sq, signal_variance)
        mean = (kern @ beta[..., None]).squeeze(-1)  # Eq. 1
        weighted = (kern @ K_inv).mul_(kern)  # k K⁻¹ ∘ k
        quad = weighted.sum(-1)  # k K⁻¹ kᵀ
        var = signal_variance[..., None] - quad  # Eq. 2
        if ctx.needs_input_grad[0]:
            # ∂k_n/∂z = k_n (d_n − z): ∂m/∂z = Σ_n β_n k_n (d_n − z), ∂v/∂z = −2 Σ_n (k K⁻¹)_n k_n (d_n − z).
            grad_mean = kern.mul_(beta[..., None, :]) @ data - z * mean[..., None]
            grad_var = (weighted @ data - z * quad[..., None]).mul_(-2.0)
            ctx.save_for_backward(grad_mean, grad_var)
        return mean, var

    @staticmethod
    @once_differentiable
    def backward(  # type: ignore[override]
        ctx: FunctionCtx, grad_mean: Tensor, grad_var: Tensor
    ) -> tuple[Tensor | None, ...]:
        mean_z, var_z = ctx.saved_tensors
        grad_z = mean_z * grad_mean[..., None] + var_z * grad_var[..., None]
        return grad_z, None, None, None, None, None


def gp_predictive(
    z: Tensor, data: Tensor, data_sq: Tensor, beta: Tensor, K_inv: Tensor, signal_variance: Tensor
) -> tuple[Tensor, Tensor]:
    """Per-output GP mean k β and latent variance α² − k K⁻¹ kᵀ at points ``z`` (Eq. 1-2).

    ``z`` `... x E x P x D` are the points over ℓ_a, ``data`` `... x E x n x D` the training
    inputs over ℓ_a, ``data_sq`` `... x E x n` their squared norms, ``beta`` `... x E x n`,
    ``K_inv`` `... x E x n x n` = (K_a + σ_ε²I)⁻¹ (symmetric), ``signal_variance`` `... x E`
    (α²). Returns mean and variance `... x E x P`; the variance may be slightly negative from
    round-off. Differentiable in ``z`` only (the data are fixed during policy search).
    """
    return _GPPredictive.apply(z, data, data_sq, beta, K_inv, signal_variance)
