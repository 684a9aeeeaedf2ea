"""Exact moments of SE-kernel regressors at Gaussian inputs (PILCO's gp0 and gp2, vectorised).

For outputs a = 1..E, f_a(x) = Σ_i β_ai k_a(x_i, x) with the ARD squared-exponential kernel
k_a(x, x') = α_a² exp(−½ (x − x')ᵀ Λ_a⁻¹ (x − x')) (Eq. 3). Under x ~ N(μ, Σ) the mean,
the covariance between all pairs of outputs and the input–output covariance are closed-form
(Deisenroth & Rasmussen 2011; Deisenroth's thesis, Sec. 2.3). With the GP's (K + σ_ε²I)⁻¹
the covariance also holds the expected posterior variance E[var_f] (gp0); without it f is a
deterministic regressor, the RBF policy of Eq. 5 (gp2).
"""

from __future__ import annotations

import torch
from torch import Tensor

from qtl.gaussian import Gaussian, MomentMatch, symmetrize
from qtl.kernels.exp_sum import weighted_exp_sum


class SEKernelMoments:
    """Moments of f_a(x) = Σ_i β_ai k_a(x_i, x), a = 1..E, at Gaussian inputs x ~ N(μ, Σ).

    ``inputs`` `... x n x D`, ``beta`` `... x E x n`, ``lengthscales`` `... x E x D` (ℓ),
    ``signal_variance`` `... x E` (α²); leading dimensions batch several regressors (several
    models) and broadcast against the batch of the Gaussian input. With ``K_inv``
    `... x E x n x n` = (K_a + σ_ε²I)⁻¹ the predictive covariance includes the expected GP
    posterior variance α_a² − tr(K_inv_a Q_aa) (PILCO gp0); without, f is a deterministic
    RBF network (gp2). Everything that depends only on these tensors is computed here, once.
    """

    def __init__(
        self,
        inputs: Tensor,
        beta: Tensor,
        lengthscales: Tensor,
        signal_variance: Tensor,
        K_inv: Tensor | None = None,
    ) -> None:
        num_out = beta.shape[-2]
        if lengthscales.shape[-2:] != (num_out, inputs.shape[-1]):
            raise ValueError(
                f"lengthscales must be `... x {num_out} x {inputs.shape[-1]}`, got {tuple(lengthscales.shape)}"
            )
        if beta.shape[-1] != inputs.shape[-2]:
            raise ValueError(f"beta has {beta.shape[-1]} columns for {inputs.shape[-2]} inputs")
        self.inputs = inputs
        self.beta = beta
        self.inv_ls = lengthscales.reciprocal()  # ... x E x D
        self.log_sf2 = signal_variance.log()  # ... x E
        self.signal_variance = signal_variance
        self.with_model_variance = K_inv is not None
        device = beta.device
        # Unordered output pairs (a <= b): the E x E second moments are symmetric, so only
        # E(E+1)/2 of them are computed, all in one batch.
        rows, cols = torch.triu_indices(num_out, num_out, device=device)
        self.pair_a, self.pair_b = rows, cols
        pair_of = torch.zeros(num_out, num_out, dtype=torch.long, device=device)
        pair_ids = torch.arange(rows.numel(), device=device)
        pair_of[rows, cols] = pair_ids
        pair_of[cols, rows] = pair_ids
        self.pair_of = pair_of.flatten()
        inv_ls2 = self.inv_ls.square()
        self.inv_ls2_a = inv_ls2[..., rows, :]  # ... x P x D, Λ_a⁻¹
        self.inv_ls2_b = inv_ls2[..., cols, :]  # ... x P x D, Λ_b⁻¹
        self.scale_ab = (self.inv_ls2_a + self.inv_ls2_b).sqrt()  # ... x P x D, √(Λ_a⁻¹ + Λ_b⁻¹)
        # Weights of the second moments, β_a β_bᵀ − [a = b] (K_a + σ²I)⁻¹: `... x P x n x n`,
        # precomputed once (P n² entries: 80 MB in float64 for E = 4, n = 1000).
        weights = beta[..., rows, :, None] * beta[..., cols, None, :]
        if K_inv is not None:
            weights = weights.index_add(weights.dim() - 3, pair_of.diagonal(), -K_inv)
        self.weights = weights

    def __call__(self, state: Gaussian) -> MomentMatch:
        """Mean `... x E`, covariance `... x E x E` and input–output terms `... x D x E`."""
        state = state.expand()
        mean, cov = state.mean, state.cov
        dim = mean.shape[-1]
        if dim != self.inputs.shape[-1]:
            raise ValueError(f"expected a {self.inputs.shape[-1]}-D input, got {dim}-D")
        eye = torch.eye(dim, dtype=mean.dtype, device=mean.device)
        nu = self.inputs[..., None, :, :] - mean[..., None, None, :]  # ... x 1 x n x D, x_i − μ

        # Mean and input–output covariance, per output a.
        inv_ls = self.inv_ls
        scaled = nu * inv_ls[..., :, None, :]  # ... x E x n x D, Λ_a^{-1/2}(x_i − μ)
        b_mat = inv_ls[..., :, :, None] * cov[..., None, :, :] * inv_ls[..., :, None, :] + eye
        chol_b = torch.linalg.cholesky(b_mat)  # ... x E x D x D
        solved = torch.cholesky_solve(scaled.mT, chol_b).mT  # B⁻¹ Λ^{-1/2} ν
        half_logdet_b = torch.diagonal(chol_b, dim1=-2, dim2=-1).log().sum(-1)
        # q_ai = α_a² |B_a|^{-1/2} exp(−½ ν_iᵀ(Σ + Λ_a)⁻¹ν_i) = E[k_a(x_i, x)].
        log_q = (self.log_sf2 - half_logdet_b)[..., None] - 0.5 * (scaled * solved).sum(-1)
        bq = self.beta * log_q.exp()  # ... x E x n
        out_mean = bq.sum(-1)  # ... x E
        gain = ((bq[..., None] * solved).sum(-2) * inv_ls).mT  # ... x D x E, (Σ + Λ_a)⁻¹ Σ_i β q ν

        # Second moments of all unordered output pairs at once (PILCO's Q matrices).
        inv_a, inv_b, scale = self.inv_ls2_a, self.inv_ls2_b, self.scale_ab
        scaled_cov = scale[..., :, None] * cov[..., None, :, :] * scale[..., None, :]
        chol_r = torch.linalg.cholesky(scaled_cov + eye)  # R̃ = D Σ D + I, D = √(Λ_a⁻¹ + Λ_b⁻¹)
        half_logdet_r = torch.diagonal(chol_r, dim1=-2, dim2=-1).log().sum(-1)  # ... x P
        # X = R̃⁻¹ D Σ D, so that ½ zᵀ R⁻¹ Σ z = ½ (D⁻¹z)ᵀ X (D⁻¹z) with z = Λ_a⁻¹ν_i + Λ_b⁻¹ν_j.
        x_mat = symmetrize(torch.cholesky_solve(scaled_cov, chol_r))
        left = nu * (inv_a / scale)[..., :, None, :]  # ... x P x n x D, D⁻¹Λ_a⁻¹ν_i
        right = nu * (inv_b / scale)[..., :, None, :]  # D⁻¹Λ_b⁻¹ν_j
        left_x = left @ x_mat
        nu2 = nu.square()
        log_sf2 = self.log_sf2
        # log Q_ij = u_i + v_j + (D⁻¹Λ_a⁻¹ν_i)ᵀ X (D⁻¹Λ_b⁻¹ν_j) − ½ log|R̃|, with
        # u_i = log α_a² − ½ ν_iᵀΛ_a⁻¹ν_i + ½ (·)ᵀX(·), and likewise v_j for output b.
        u = (
            log_sf2[..., self.pair_a, None]
            - 0.5 * (nu2 * inv_a[..., :, None, :]).sum(-1)
            + 0.5 * (left_x * left).sum(-1)
        )
        v = (
            log_sf2[..., self.pair_b, None]
            - 0.5 * (nu2 * inv_b[..., :, None, :]).sum(-1)
            + 0.5 * ((right @ x_mat) * right).sum(-1)
        )
        ones = torch.ones_like(u)[..., None]
        lhs = torch.cat([left_x, u[..., None], ones], dim=-1)  # ... x P x n x (D + 2)
        rhs = torch.cat([right, ones, v[..., None]], dim=-1)
        second = torch.exp(-half_logdet_r) * weighted_exp_sum(lhs, rhs, self.weights)  # ... x P
        num_out = out_mean.shape[-1]
        second = second[..., self.pair_of].unflatten(-1, (num_out, num_out))
        out_cov = second - out_mean[..., :, None] * out_mean[..., None, :]
        if self.with_model_variance:
            out_cov = out_cov + torch.diag_embed(self.signal_variance).to(out_cov)
        return MomentMatch(mean=out_mean, cov=symmetrize(out_cov), cross_cov=cov @ gain, gain=gain)
