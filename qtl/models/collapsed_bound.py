"""Titsias' collapsed bound of the sparse GP (SGPR, Titsias 2009, Eq. 9) with its gradient in closed form.

Per output, with K_fu `n x m` the SE cross-covariance (Eq. 3) of the data X and the inducing inputs Z, K_uu + δI =
L Lᵀ (δ = jitter · α²), Ã = L⁻¹ K_uf, P = Ã Ãᵀ, r = Ã y, B = I + P / σ² = L_B L_Bᵀ and β = B⁻¹ r:

    F = log N(y | 0, K_fu K_uu⁻¹ K_uf + σ²I) − tr(K_ff − K_fu K_uu⁻¹ K_uf) / (2σ²)
      = −n/2 log 2π − n/2 log σ² − log |L_B| − yᵀy / (2σ²) + rᵀβ / (2σ⁴) − (n α² − tr P) / (2σ²)

(the log density by Woodbury, the value GPyTorch's ``InducingPointKernel`` gives). Its gradient, with
S = 2 ∂F/∂P = (I − B⁻¹ − ββᵀ/σ⁴) / σ² and g = ∂F/∂r = β / σ⁴:

    ∂F/∂K_uf = L⁻ᵀ (S Ã + g yᵀ),    ∂F/∂K_uu = −½ L⁻ᵀ (P S + r gᵀ) L⁻¹ (P S + r gᵀ = Ã (∂F/∂Ã)ᵀ, symmetric),
    ∂F/∂σ² = −n/(2σ²) + σ²(m − tr B⁻¹)/(2σ⁴) + yᵀy/(2σ⁴) + βᵀPβ/(2σ⁸) − rᵀβ/σ⁶ + (n α² − tr P)/(2σ⁴),

then to α², ℓ and Z through the kernel in closed form (W = ∂F/∂K ∘ K). One evaluation with its gradient forms
three `E x n x m` products (Ã by a triangular solve, P, S Ã) and one more solve; GPyTorch's autograd through the
same bound forms about twice that, a dozen elementwise passes over `E x n x m`, and the backward of two Cholesky
factorisations. β is B⁻¹ r by two triangular solves, never by B⁻¹ times r: r lies along B's large eigenvalues
(~1e8 once learned Z crowd the data) and the explicit product would lose the gradient to O(1) relative error.

Per-point noise λ_i = σ² + c_i (c fixed, :mod:`qtl.models.point_noise`), Λ = diag(λ): since Q + Λ = Λ^{1/2} (Q̃ + I)
Λ^{1/2} with Q̃ the Nyström matrix of the rows K̃_fu = Λ^{-1/2} K_fu, F = log N(y | 0, Q + Λ) − ½ tr(Λ⁻¹ (K_ff − Q))
is the bound above at σ² = 1 of those rows and ỹ = Λ^{-1/2} y, with n α² replaced by α² Σ_i 1/λ_i and −n/2 log σ²
by −½ Σ_i log λ_i. Its gradient in K̃_fu and K_uu is the one above at σ² = 1, and ∂F/∂K_fu ∘ K_fu = ∂F/∂K̃_fu ∘ K̃_fu
(the row scale cancels), so ℓ, Z and α² go through W unchanged (n/σ² → Σ_i 1/λ_i in α²'s explicit term). σ² moves
every λ_i, hence K̃_fu and ỹ (∂K̃_ij/∂λ_i = −K̃_ij / (2λ_i)): with W_i = Σ_j W_ij and f̃ = Ãᵀ β the scaled fit,

    ∂F/∂σ² = Σ_i ∂F/∂λ_i = Σ_i [−(W_i + ỹ_i (f̃_i − ỹ_i)) / (2λ_i) − 1/(2λ_i) + α² / (2λ_i²)].
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
    log_scale = signal_variance.log()[:, None]
    # log K = (log α² − ½|x|²) + (−½|z|²) + xᵀz: one broadcast sum of two vectors, one batched product onto it.
    offset = (log_scale - 0.5 * x.square().sum(-1))[:, :, None] + (-0.5 * z.square().sum(-1))[:, None, :]
    return torch.baddbmm(offset, x, z.mT).clamp_max_(log_scale[..., None]).exp_()


def _spread(row: Tensor, col: Tensor, weighted: Tensor, z: Tensor, x: Tensor) -> Tensor:
    """Σ_ij W_ij (x_id − z_jd)² per output and input dimension `E x D`, expanded, from W's sums.

    row_j = Σ_i W_ij `E x m`, col_i = Σ_j W_ij `E x n`, weighted_jd = Σ_i W_ij x_id `E x m x D`; Z `m x D`, X `n x D`.
    """
    return (row[:, None, :] @ z.square()).squeeze(-2) - 2 * (z * weighted).sum(-2) \
        + (col[:, None, :] @ x.square()).squeeze(-2)


class CollapsedBound(torch.autograd.Function):
    """F per output `E` and its backward in closed form (module docstring).

    Inputs: ℓ `E x D`, α² `E`, σ² `E`, Z `m x D` (shared by the outputs), X `n x D`, y `E x n`, the jitter δ / α²,
    the per-point extra noise c `E x n` (or None). X, y and c are data: no gradient flows to them. With c, K_fu, y
    and the noise saved are the rows over √λ and 1. K_fu and Ãᵀ are held `E x n x m`, the layout in which the
    triangular solves and the products need no copies.
    """

    @staticmethod
    def forward(ctx, lengthscales: Tensor, signal_variance: Tensor, noise_variance: Tensor, inducing: Tensor,
                inputs: Tensor, targets: Tensor, jitter: float, extra_noise: Tensor | None = None) -> Tensor:
        centre = inputs.mean(0)  # the kernel is stationary: centring keeps the expansion's cancellation small
        x, z = inputs - centre, inducing - centre
        n, m = x.shape[0], z.shape[0]
        eye = torch.eye(m, dtype=x.dtype, device=x.device)
        k_uu = se_cross_covariance(z, z, lengthscales, signal_variance)  # E x m x m
        chol = psd_safe_cholesky(k_uu + (jitter * signal_variance)[:, None, None] * eye)
        k_fu = se_cross_covariance(x, z, lengthscales, signal_variance)  # E x n x m
        point = None  # λ = σ² + c `E x n` with per-point noise
        if extra_noise is not None:  # the rows over √λ at unit noise (module docstring)
            point = noise_variance[:, None] + extra_noise
            row_scale = point.rsqrt()
            k_fu = k_fu.mul_(row_scale[..., None])
            targets = targets * row_scale
            noise_variance = torch.ones_like(noise_variance)
        a = torch.linalg.solve_triangular(chol.mT, k_fu, upper=True, left=False)  # Ãᵀ = K_fu L⁻ᵀ
        p = a.mT @ a
        r = (targets[:, None, :] @ a).squeeze(-2)  # E x m
        noise = noise_variance[:, None, None]
        chol_b = psd_safe_cholesky(eye + p / noise)
        c = torch.linalg.solve_triangular(chol_b, r[..., None], upper=False).squeeze(-1)  # L_B⁻¹ r: |c|² = rᵀβ
        yy = targets.square().sum(-1)
        trace_p = p.diagonal(dim1=-2, dim2=-1).sum(-1)
        # ½ log |Λ| and tr(K_ff) / α² over the noise: ½ n log σ² and n, or ½ Σ_i log λ_i and Σ_i 1/λ_i.
        log_noise = 0.5 * n * noise_variance.log() if point is None else 0.5 * point.log().sum(-1)
        count = n if point is None else point.reciprocal().sum(-1)
        value = (-0.5 * n * math.log(2 * math.pi) - log_noise
                 - chol_b.diagonal(dim1=-2, dim2=-1).log().sum(-1)
                 - 0.5 * (yy - c.square().sum(-1) / noise_variance) / noise_variance
                 - 0.5 * (count * signal_variance - trace_p) / noise_variance)
        ctx.jitter = jitter
        ctx.save_for_backward(lengthscales, signal_variance, noise_variance, z, x, targets, k_uu, k_fu, a, chol, p, r,
                              chol_b, yy, trace_p, point)
        return value

    @staticmethod
    def backward(ctx, grad_value: Tensor) -> tuple[Tensor | None, ...]:
        ls, sv, nv, z, x, y, k_uu, k_fu, a, chol, p, r, chol_b, yy, trace_p, point = ctx.saved_tensors
        n, m = x.shape[0], z.shape[0]
        eye = torch.eye(m, dtype=x.dtype, device=x.device)
        noise, scale = nv[:, None, None], grad_value[:, None, None]
        b_inv = torch.cholesky_inverse(chol_b)
        beta = torch.cholesky_solve(r[..., None], chol_b)  # B⁻¹ r by solves (module docstring), E x m x 1
        outer = beta @ beta.mT / noise.square()  # ββᵀ/σ⁴
        s = (eye - b_inv - outer) / noise * scale  # S
        g = beta.mT / noise.square() * scale  # gᵀ, E x 1 x m
        # ∂F/∂K_fu = (S Ã + g yᵀ)ᵀ L⁻¹, from (∂F/∂Ã)ᵀ = Ãᵀ S + y gᵀ `E x n x m` (rank-1 update and solve in place).
        grad_fu = (a @ s).baddbmm_(y[..., None], g)
        torch.linalg.solve_triangular(chol, grad_fu, upper=False, left=False, out=grad_fu)
        # ∂F/∂K_uu = −½ L⁻ᵀ C L⁻¹ with C = P S + r gᵀ, symmetrised.
        c = (p @ s).baddbmm_(r[..., None], g)
        c = 0.5 * (c + c.mT)
        grad_uu = -0.5 * torch.linalg.solve_triangular(chol, torch.linalg.solve_triangular(chol.mT, c, upper=True),
                                                       upper=False, left=False)
        grad_uu = 0.5 * (grad_uu + grad_uu.mT)
        if point is None:  # ∂F/∂σ² with P and r held.
            quad_p = (beta.mT @ p @ beta).flatten(-3)  # βᵀPβ
            r_beta = (r[:, None, :] @ beta).flatten(-3)  # rᵀβ
            grad_noise = (-0.5 * n / nv + 0.5 * (m - b_inv.diagonal(dim1=-2, dim2=-1).sum(-1)) / nv
                          + 0.5 * yy / nv**2 + 0.5 * quad_p / nv**4 - r_beta / nv**3
                          + 0.5 * (n * sv - trace_p) / nv**2) * grad_value
            count = n
        else:  # ∂F/∂σ² = Σ_i ∂F/∂λ_i through the scaled rows, after W (module docstring)
            count = point.reciprocal().sum(-1)
            fit = (a @ beta).squeeze(-1)  # f̃ = Ãᵀ β `E x n`, Ã of the scaled rows
            pull = y * (fit - y) * grad_value[:, None]  # ỹ_i ∂F/∂ỹ_i
        # Through the kernels K = α² exp(−½ Σ_d (a_d − b_d)² / ℓ_d²), with W = ∂F/∂K ∘ K.
        w_fu = grad_fu.mul_(k_fu)  # E x n x m (in place: ∂F/∂K_fu is not needed again)
        w_uu = grad_uu * k_uu  # E x m x m, symmetric
        fu_row, fu_col, fu_x = w_fu.sum(-2), w_fu.sum(-1), w_fu.mT @ x  # E x m, E x n, E x m x D
        uu_row, uu_z = w_uu.sum(-1), w_uu @ z  # E x m, E x m x D
        inv_sq = ls.square().reciprocal()  # E x D
        grad_signal = ((fu_row.sum(-1) + uu_row.sum(-1)) / sv
                       + ctx.jitter * grad_uu.diagonal(dim1=-2, dim2=-1).sum(-1) - 0.5 * count / nv * grad_value)
        if point is not None:  # W_i = fu_col_i = Σ_j ∂F/∂K̃_ij K̃_ij
            inv = point.reciprocal()
            grad_noise = (-0.5 * (inv * (fu_col + pull)).sum(-1)
                          + 0.5 * (sv * inv.square().sum(-1) - count) * grad_value)
        # ∂F/∂z_jd = −Σ_e [Σ_i W^fu_eij (z_jd − x_id) + 2 Σ_k W^uu_ejk (z_jd − z_kd)] / ℓ_ed²
        pull = (z * fu_row[..., None] - fu_x) + 2 * (z * uu_row[..., None] - uu_z)
        grad_inducing = -(pull * inv_sq[:, None, :]).sum(0)
        # ∂F/∂ℓ_ed = [Σ_ij W^fu_eij (x_id − z_jd)² + Σ_jk W^uu_ejk (z_jd − z_kd)²] / ℓ_ed³
        spread = _spread(fu_row, fu_col, fu_x, z, x) + _spread(uu_row, uu_row, uu_z, z, z)
        grad_lengthscales = spread * inv_sq / ls
        return grad_lengthscales, grad_signal, grad_noise, grad_inducing, None, None, None, None


def collapsed_bound(inputs: Tensor, targets: Tensor, inducing: Tensor, lengthscales: Tensor, signal_variance: Tensor,
                    noise_variance: Tensor, jitter: float, extra_noise: Tensor | None = None) -> Tensor:
    """F per output `E` (Titsias 2009, Eq. 9): X `n x D`, y `E x n`, Z `m x D`, ℓ `E x D`, α² `E`, σ² `E`.

    ``extra_noise``: c `E x n`, point i of output e observed with noise σ² + c_ei (None: σ² for every point).

    K_uu carries δ = ``jitter`` · α² on its diagonal (as :class:`qtl.models.SparseDynamicsGP`). Differentiable in
    ℓ, α², σ² and Z. Raises linear_operator's ``NotPSDError`` where K_uu + δI is not factorisable even with the
    extra jitter GPyTorch adds.
    """
    return CollapsedBound.apply(lengthscales, signal_variance, noise_variance, inducing, inputs, targets, jitter,
                                extra_noise)
