"""Titsias' collapsed bound of the sparse GP (SGPR, Titsias 2009) with its gradient, in three `E x m x n` products.

Per output, with K_uf `m x n` the SE cross-covariance (Eq. 3) of the inducing inputs Z and the data X, L the
Cholesky factor of K_uu + δI, Ã = L⁻¹ K_uf, P = Ã Ãᵀ, r = Ã y and B = I + P / σ² = L_B L_Bᵀ:

    F = log N(y | 0, K_fu K_uu⁻¹ K_uf + σ²I) − tr(K_ff − K_fu K_uu⁻¹ K_uf) / (2σ²)
      = −n/2 log 2π − n/2 log σ² − Σ log diag L_B − (yᵀy − |L_B⁻¹ r|² / σ²) / (2σ²) − (n α² − tr P) / (2σ²)

(the log density by Woodbury, as GPyTorch's ``InducingPointKernel`` evaluates it). Everything after (P, r) is
`m x m` and goes through autograd; (P, r) come from :class:`ProjectedCrossCovariance`, whose backward gives
∂F/∂K_uf = L⁻ᵀ (S L⁻¹ K_uf + g yᵀ) with S = G_P + G_Pᵀ and g = G_r in one product, ∂F/∂L from `m x m` factors
(Ã ∂F/∂Ãᵀ = S P + g rᵀ), and the chain rule to α², ℓ and Z in closed form, so the `E x m x n` work of one
evaluation and its gradient is Ã (a triangular solve), P (a product) and ∂F/∂K_uf (a product), plus K_uf itself.
GPyTorch's autograd through the same bound forms about twice the products and a dozen elementwise passes.
"""

from __future__ import annotations

import math

import torch
from linear_operator.utils.cholesky import psd_safe_cholesky
from torch import Tensor


def se_cross_covariance(inputs: Tensor, inducing: Tensor, lengthscales: Tensor, signal_variance: Tensor) -> Tensor:
    """K_fu = α² exp(−½ Σ_d (x_d − z_d)² / ℓ_d²) (Eq. 3): `E x n x m` from X `n x D`, Z `m x D`, ℓ `E x D`, α² `E`.

    Squared distances by the expansion |x|² + |z|² − 2 xᵀz of the scaled inputs, clamped at 0 (as GPyTorch).
    """
    x = inputs / lengthscales[:, None, :]  # E x n x D
    z = inducing / lengthscales[:, None, :]  # E x m x D
    log_scale = signal_variance.log()[:, None, None]
    # log K = log α² − ½ (|x|² + |z|²) + xᵀz: one batched product on top of the broadcast sum.
    offset = log_scale - 0.5 * (x.square().sum(-1)[:, :, None] + z.square().sum(-1)[:, None, :])
    return torch.baddbmm(offset, x, z.mT).clamp_max_(log_scale).exp_()


class ProjectedCrossCovariance(torch.autograd.Function):
    """(P, r) = (Ã Ãᵀ, Ã y) with Ã = L⁻¹ K_uf: P `E x m x m`, r `E x m`, and their backward in closed form.

    Inputs: ℓ `E x D`, α² `E`, Z `m x D` (shared by the outputs), L `E x m x m` (lower), X `n x D`, y `E x n`.
    X and y are data: no gradient flows to them. Ã is held transposed, `E x n x m`, the layout in which the
    triangular solve and the products need no copies.
    """

    @staticmethod
    def forward(ctx, lengthscales: Tensor, signal_variance: Tensor, inducing: Tensor, chol: Tensor,
                inputs: Tensor, targets: Tensor) -> tuple[Tensor, Tensor]:
        centre = inputs.mean(0)  # the kernel is stationary: centring keeps the expansion's cancellation small
        x, z = inputs - centre, inducing - centre
        k = se_cross_covariance(x, z, lengthscales, signal_variance)  # K_fu, E x n x m
        a = torch.linalg.solve_triangular(chol.mT, k, upper=True, left=False)  # Ãᵀ = K_fu L⁻ᵀ
        p = a.mT @ a
        r = (targets[:, None, :] @ a).squeeze(-2)
        ctx.save_for_backward(lengthscales, signal_variance, z, chol, x, targets, k, a, p, r)
        return p, r

    @staticmethod
    def backward(ctx, grad_p: Tensor, grad_r: Tensor) -> tuple[Tensor | None, ...]:
        lengthscales, signal_variance, z, chol, x, targets, k, a, p, r = ctx.saved_tensors
        s = grad_p + grad_p.mT  # E x m x m
        # ∂F/∂Ã = S Ã + g yᵀ, ∂F/∂K_uf = L⁻ᵀ ∂F/∂Ã and ∂F/∂L = −L⁻ᵀ (∂F/∂Ã) Ãᵀ = −L⁻ᵀ (S P + g rᵀ), lower
        # triangle. Solves, not products with L⁻ᵀ S or L⁻ᵀ S L⁻¹: with K_uu near singular (learned Z crowd the data)
        # those are huge and cancel against Ã or K_uf, to 1e-5 or 1e-2 relative in the gradient.
        grad_a = torch.baddbmm(targets[..., None] * grad_r[:, None, :], a, s)  # (∂F/∂Ã)ᵀ, E x n x m
        grad_k = torch.linalg.solve_triangular(chol, grad_a, upper=False, left=False)  # ∂F/∂K_fu = (∂F/∂Ã)ᵀ L⁻¹
        grad_chol = -torch.linalg.solve_triangular(chol.mT, torch.baddbmm(grad_r[..., None] * r[:, None, :], s, p),
                                                   upper=True).tril_()
        # Chain rule through K = α² exp(−½ Σ_d (x_d − z_d)² / ℓ_d²), with W = ∂F/∂K_fu ∘ K_fu.
        w = grad_k.mul_(k)  # E x n x m (in place: ∂F/∂K is not needed again)
        per_inducing = w.sum(-2)  # E x m
        per_input = w.sum(-1)  # E x n
        wx = w.mT @ x  # E x m x D: Σ_i W_ij x_i
        inv_sq = lengthscales.square().reciprocal()  # E x D
        grad_signal = per_inducing.sum(-1) / signal_variance
        # ∂F/∂z_jd = −Σ_e Σ_i W_eij (z_jd − x_id) / ℓ_ed²
        grad_inducing = -((z * per_inducing[..., None] - wx) * inv_sq[:, None, :]).sum(0)
        # ∂F/∂ℓ_ed = Σ_ij W_eij (x_id − z_jd)² / ℓ_ed³
        spread = (per_inducing[:, None, :] @ z.square()).squeeze(-2) - 2 * (z * wx).sum(-2) \
            + (per_input[:, None, :] @ x.square()).squeeze(-2)  # E x D
        grad_lengthscales = spread * inv_sq / lengthscales
        return grad_lengthscales, grad_signal, grad_inducing, grad_chol, None, None


def collapsed_bound(inputs: Tensor, targets: Tensor, inducing: Tensor, lengthscales: Tensor, signal_variance: Tensor,
                    noise_variance: Tensor, jitter: float) -> Tensor:
    """F per output `E` (Titsias 2009, Eq. 9): X `n x D`, y `E x n`, Z `m x D`, ℓ `E x D`, α² `E`, σ² `E`.

    K_uu carries δ = ``jitter`` · α² on its diagonal (as :class:`qtl.models.SparseDynamicsGP`). Differentiable in
    ℓ, α², σ² and Z. Raises linear_operator's ``NotPSDError`` where K_uu + δI is not factorisable even with the
    extra jitter GPyTorch adds.
    """
    n = inputs.shape[0]
    z = inducing / lengthscales[:, None, :]
    sq = (z.square().sum(-1)[:, :, None] + z.square().sum(-1)[:, None, :] - 2 * z @ z.mT).clamp_min(0)
    k_uu = signal_variance[:, None, None] * torch.exp(-0.5 * sq)
    if jitter:
        eye = torch.eye(inducing.shape[0], dtype=inputs.dtype, device=inputs.device)
        k_uu = k_uu + (jitter * signal_variance)[:, None, None] * eye
    chol = psd_safe_cholesky(k_uu)
    p, r = ProjectedCrossCovariance.apply(lengthscales, signal_variance, inducing, chol, inputs, targets)
    eye = torch.eye(p.shape[-1], dtype=p.dtype, device=p.device)
    chol_b = psd_safe_cholesky(eye + p / noise_variance[:, None, None])
    c = torch.linalg.solve_triangular(chol_b, r[..., None], upper=False).squeeze(-1)  # L_B⁻¹ r
    half_logdet = chol_b.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    quad = (targets.square().sum(-1) - c.square().sum(-1) / noise_variance) / noise_variance
    trace = (n * signal_variance - p.diagonal(dim1=-2, dim2=-1).sum(-1)) / noise_variance
    return -0.5 * n * math.log(2 * math.pi) - 0.5 * n * noise_variance.log() - half_logdet - 0.5 * quad - 0.5 * trace
