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
from torch.autograd.function import once_differentiable

from qtl.gaussian import Gaussian, MomentMatch, batch_matmul, cholesky, full_batch, identity, nan_where, symmetrize
from qtl.kernels.engine import DEFAULT_ENGINE, Engine
from qtl.kernels.exp_sum import weighted_exp_sum
from qtl.kernels.native.se_moments import native_fits, se_kernel_moments


class _InverseHalfLogdet(torch.autograd.Function):
    """(M⁻¹, ½ log|M|) of symmetric positive-definite M `... x D x D` by one Cholesky factorisation.

    The backward pass is the closed form d(M⁻¹) = −M⁻¹ dM M⁻¹, d(½ log|M|) = ½ tr(M⁻¹ dM),
    symmetrized as torch's Cholesky backward is: a few matrix products instead of the graph
    of a factorisation, its solves and a log-determinant. A non-positive-definite M raises
    ``torch.linalg.LinAlgError``, as ``torch.linalg.cholesky`` does, or inside
    :func:`qtl.gaussian.element_failures` makes its element's results (and gradients) NaN; ``inner``: the
    trailing batch dimensions of one element (:func:`qtl.gaussian.cholesky`).
    """

    @staticmethod
    def forward(ctx, mat: Tensor, inner: int) -> tuple[Tensor, Tensor]:  # type: ignore[override]
        chol, failed = cholesky(mat, inner)
        inverse = nan_where(failed, torch.cholesky_inverse(chol))  # exactly symmetric
        ctx.save_for_backward(inverse)
        return inverse, nan_where(failed, torch.diagonal(chol, dim1=-2, dim2=-1).log().sum(-1))

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_inverse: Tensor, grad_half_logdet: Tensor) -> tuple[Tensor, None]:  # type: ignore[override]
        (inverse,) = ctx.saved_tensors
        flat = inverse.reshape(-1, *inverse.shape[-2:])
        sandwich = torch.bmm(torch.bmm(flat, grad_inverse.reshape(flat.shape)), flat).view(inverse.shape)
        grad = torch.addcmul(-sandwich, inverse, 0.5 * grad_half_logdet[..., None, None])
        return symmetrize(grad), None


def inverse_and_half_logdet(mat: Tensor, inner: int = 0) -> tuple[Tensor, Tensor]:
    """M⁻¹ `... x D x D` and ½ log|M| `...` of symmetric positive-definite ``mat`` (one Cholesky factorisation)."""
    return _InverseHalfLogdet.apply(mat, inner)


class SEKernelMoments:
    """Moments of f_a(x) = Σ_i β_ai k_a(x_i, x), a = 1..E, at Gaussian inputs x ~ N(μ, Σ).

    ``inputs`` `... x n x D`, ``beta`` `... x E x n`, ``lengthscales`` `... x E x D` (ℓ),
    ``signal_variance`` `... x E` (α²); leading dimensions batch several regressors (several
    models) and broadcast against the batch of the Gaussian input. With ``K_inv``
    `... x E x n x n` = (K_a + σ_ε²I)⁻¹ the predictive covariance includes the expected GP
    posterior variance α_a² − tr(K_inv_a Q_aa) (PILCO gp0); without, f is a deterministic
    RBF network (gp2). Everything that depends only on these tensors is computed here, once,
    in the shapes the per-call arithmetic broadcasts against. A call follows ``engine``
    (:class:`qtl.kernels.engine.Engine`): ``reference`` factorises B_a and R̃_ab separately,
    ``fused`` inverts them in one batch with a closed-form backward and uses X = I − R̃⁻¹.
    """

    def __init__(
        self,
        inputs: Tensor,
        beta: Tensor,
        lengthscales: Tensor,
        signal_variance: Tensor,
        K_inv: Tensor | None = None,
        *,
        engine: Engine = DEFAULT_ENGINE,
    ) -> None:
        num_out = beta.shape[-2]
        if lengthscales.shape[-2:] != (num_out, inputs.shape[-1]):
            raise ValueError(
                f"lengthscales must be `... x {num_out} x {inputs.shape[-1]}`, got {tuple(lengthscales.shape)}"
            )
        if beta.shape[-1] != inputs.shape[-2]:
            raise ValueError(f"beta has {beta.shape[-1]} columns for {inputs.shape[-2]} inputs")
        self.engine = engine
        self.inputs = inputs
        self.beta = beta
        self.inv_ls = lengthscales.reciprocal()  # ... x E x D
        self.log_sf2 = signal_variance.log()  # ... x E
        self.signal_variance = signal_variance
        self.with_model_variance = K_inv is not None
        device = beta.device
        self.num_out = num_out
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

        # Broadcast-ready constants of __call__ (`...` the regressors' batch).
        self._inputs = inputs[..., None, :, :]  # ... x 1 x n x D
        self._inv_ls_row = self.inv_ls[..., :, None, :]  # ... x E x 1 x D
        # B_a = Λ_a^{-1/2} Σ Λ_a^{-1/2} + I and R̃_ab = D Σ D + I, D = √(Λ_a⁻¹ + Λ_b⁻¹), are both
        # diag(c) Σ diag(c) + I: their c ⊗ c, stacked (`... x (E + P) x D x D`), factorised in one call.
        scales = torch.cat([self.inv_ls, self.scale_ab], dim=-2)
        self._scales_outer = scales[..., :, :, None] * scales[..., :, None, :]
        # Per pair, the a-side then the b-side: Λ_a⁻¹ and D⁻¹Λ_a⁻¹ (`... x P x 2 x 1 x D`), log α_a²
        # (`... x P x 2 x 1`).
        self._inv_ab = torch.stack([self.inv_ls2_a, self.inv_ls2_b], dim=-2)[..., None, :]
        self._left_right = torch.stack([self.inv_ls2_a / self.scale_ab, self.inv_ls2_b / self.scale_ab], dim=-2)[
            ..., None, :
        ]
        self._log_sf2_ab = torch.stack([self.log_sf2[..., rows], self.log_sf2[..., cols]], dim=-1)[..., None]
        # The a-side carries X (left_x), the b-side not; appended columns [u, 1] and [1, v].
        self._is_a = torch.tensor([True, False], device=device)[:, None, None]
        one_hot = torch.eye(2, dtype=beta.dtype, device=device)
        self._append_scale, self._append_shift = one_hot[:, None, :], one_hot.flip(-1)[:, None, :]
        # E[var_f] contributes diag(α_a²) to the covariance.
        self._model_variance = torch.diag_embed(signal_variance) if self.with_model_variance else None
        # Weights of the second moments, β_a β_bᵀ − [a = b] (K_a + σ²I)⁻¹: `... x P x n x n`,
        # precomputed once (P n² entries: 80 MB in float64 for E = 4, n = 1000).
        weights = beta[..., rows, :, None] * beta[..., cols, None, :]
        if K_inv is not None:
            weights = weights.index_add(weights.dim() - 3, pair_of.diagonal(), -K_inv)
        self.weights = weights

    def _check_dim(self, state: Gaussian) -> None:
        """A ValueError unless the input is `D`-dimensional, as the regressor's inputs."""
        if state.dim != self.inputs.shape[-1]:
            raise ValueError(f"expected a {self.inputs.shape[-1]}-D input, got {state.dim}-D")

    def __call__(self, state: Gaussian) -> MomentMatch:
        """Mean `... x E`, covariance `... x E x E` and input–output terms `... x D x E`."""
        self._check_dim(state)
        if not self.engine.fused:
            state = state.expand()
            return self._reference_call(state.mean, state.cov)
        state = full_batch(state)
        mean, cov, gain = self._fused_call(state.mean, state.cov, self.engine)
        return MomentMatch(mean=mean, cov=cov, cross_cov=batch_matmul(state.cov, gain), gain=gain)

    def mean_cov_gain(self, state: Gaussian) -> tuple[Tensor, Tensor, Tensor]:
        """Mean `... x E`, covariance `... x E x E` and gain Σ⁻¹ cov[x, f] `... x D x E`: all but cov[x, f]."""
        if not self.engine.fused:
            out = self(state)
            return out.mean, out.cov, out.gain
        self._check_dim(state)
        return self._fused_call(state.mean, state.cov, self.engine)

    def _fused_call(self, mean: Tensor, cov: Tensor, engine: Engine) -> tuple[Tensor, Tensor, Tensor]:
        """Mean, covariance and gain, fused formulation (one factorisation of all B_a and R̃_ab, constant maps).

        Under ``engine.moments="native"`` (float64 CPU operands) one compiled call forward and one backward compute
        the same; ``engine.exp_sums`` picks the exp sums' code otherwise.
        """
        constants = (self.inputs, self.beta, self.inv_ls, self.log_sf2, self.weights)
        if engine.native and self.inputs.shape[-2] > 0 and native_fits(mean, cov, *constants):
            out_mean, out_cov, gain = se_kernel_moments(mean, cov, *constants, lower_pairs=engine.lower_pairs)
            if self._model_variance is not None:
                out_cov = out_cov + self._model_variance
            return out_mean, out_cov, gain
        eye = identity(mean.shape[-1], mean.dtype, mean.device)
        nu = self._inputs - mean[..., None, None, :]  # ... x 1 x n x D, x_i − μ

        # B_a (mean, per output a) and R̃_ab (second moments, per pair), diag(c) Σ diag(c) + I, inverted at once.
        inverses, half_logdets = inverse_and_half_logdet(self._scales_outer * cov[..., None, :, :] + eye, 1)
        num_out = self.num_out

        # Mean and input–output covariance, per output a.
        scaled = nu * self._inv_ls_row  # ... x E x n x D, Λ_a^{-1/2}(x_i − μ)
        solved = batch_matmul(scaled, inverses[..., :num_out, :, :])  # B⁻¹ Λ^{-1/2} ν (B symmetric)
        # q_ai = α_a² |B_a|^{-1/2} exp(−½ ν_iᵀ(Σ + Λ_a)⁻¹ν_i) = E[k_a(x_i, x)].
        log_norm = (self.log_sf2 - half_logdets[..., :num_out])[..., None]
        log_q = torch.add(log_norm, (scaled * solved).sum(-1), alpha=-0.5)
        bq = self.beta * log_q.exp()  # ... x E x n
        out_mean = bq.sum(-1)  # ... x E
        gain = ((bq[..., None] * solved).sum(-2) * self.inv_ls).mT  # ... x D x E, (Σ + Λ_a)⁻¹ Σ_i β q ν

        # Second moments of all unordered output pairs at once (PILCO's Q matrices).
        # X = R̃⁻¹ D Σ D = I − R̃⁻¹ (exactly symmetric), so that ½ zᵀ R⁻¹ Σ z = ½ (D⁻¹z)ᵀ X (D⁻¹z)
        # with z = Λ_a⁻¹ν_i + Λ_b⁻¹ν_j.
        x_mat = eye - inverses[..., num_out:, :, :]
        # Both sides of each pair at once (`... x P x 2 x n x D`): D⁻¹Λ_a⁻¹ν_i and D⁻¹Λ_b⁻¹ν_j.
        sides = nu[..., None, :, :] * self._left_right
        num, num_in = nu.shape[-2], sides.shape[-3]
        sides_x = batch_matmul(sides.flatten(-3, -2), x_mat).unflatten(-2, (num_in, num))
        # log Q_ij = u_i + v_j + (D⁻¹Λ_a⁻¹ν_i)ᵀ X (D⁻¹Λ_b⁻¹ν_j) − ½ log|R̃|, with
        # u_i = log α_a² − ½ ν_iᵀΛ_a⁻¹ν_i + ½ (·)ᵀX(·), and likewise v_j for output b.
        quad = (sides_x * sides - nu.square()[..., None, :, :] * self._inv_ab).sum(-1)
        uv = torch.add(self._log_sf2_ab, quad, alpha=0.5)  # ... x P x 2 x n
        # lhs = [X D⁻¹Λ_a⁻¹ν_i, u_i, 1], rhs = [D⁻¹Λ_b⁻¹ν_j, 1, v_j]: ... x P x n x (D + 2) each.
        appended = torch.addcmul(self._append_shift, uv[..., None], self._append_scale)
        operands = torch.cat([torch.where(self._is_a, sides_x, sides), appended], dim=-1)
        second = torch.exp(-half_logdets[..., num_out:]) * weighted_exp_sum(
            operands.select(-3, 0), operands.select(-3, 1), self.weights, engine=engine
        )  # ... x P
        # Spread to E x E, then the covariance: symmetric by construction (second[a, b] is second[b, a]).
        out_cov = second.index_select(-1, self.pair_of).unflatten(-1, (num_out, num_out))
        out_cov = out_cov - out_mean[..., :, None] * out_mean[..., None, :]
        if self._model_variance is not None:
            out_cov = out_cov + self._model_variance
        return out_mean, out_cov, gain

    def _reference_call(self, mean: Tensor, cov: Tensor) -> MomentMatch:
        """:meth:`__call__`, reference formulation: two Cholesky factorisations and solves, outer products."""
        dim = mean.shape[-1]
        eye = torch.eye(dim, dtype=mean.dtype, device=mean.device)
        nu = self.inputs[..., None, :, :] - mean[..., None, None, :]  # ... x 1 x n x D, x_i − μ

        # Mean and input–output covariance, per output a.
        inv_ls = self.inv_ls
        scaled = nu * inv_ls[..., :, None, :]  # ... x E x n x D, Λ_a^{-1/2}(x_i − μ)
        b_mat = inv_ls[..., :, :, None] * cov[..., None, :, :] * inv_ls[..., :, None, :] + eye
        chol_b, failed_b = cholesky(b_mat, 1)  # ... x E x D x D; a failed element: NaN from its log-determinant on
        solved = torch.cholesky_solve(scaled.mT, chol_b).mT  # B⁻¹ Λ^{-1/2} ν
        half_logdet_b = nan_where(failed_b, torch.diagonal(chol_b, dim1=-2, dim2=-1).log().sum(-1))
        # q_ai = α_a² |B_a|^{-1/2} exp(−½ ν_iᵀ(Σ + Λ_a)⁻¹ν_i) = E[k_a(x_i, x)].
        log_q = (self.log_sf2 - half_logdet_b)[..., None] - 0.5 * (scaled * solved).sum(-1)
        bq = self.beta * log_q.exp()  # ... x E x n
        out_mean = bq.sum(-1)  # ... x E
        gain = ((bq[..., None] * solved).sum(-2) * inv_ls).mT  # ... x D x E, (Σ + Λ_a)⁻¹ Σ_i β q ν

        # Second moments of all unordered output pairs at once (PILCO's Q matrices).
        inv_a, inv_b, scale = self.inv_ls2_a, self.inv_ls2_b, self.scale_ab
        scaled_cov = scale[..., :, None] * cov[..., None, :, :] * scale[..., None, :]
        chol_r, failed_r = cholesky(scaled_cov + eye, 1)  # R̃ = D Σ D + I, D = √(Λ_a⁻¹ + Λ_b⁻¹)
        half_logdet_r = nan_where(failed_r, torch.diagonal(chol_r, dim1=-2, dim2=-1).log().sum(-1))  # ... x P
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
        second = torch.exp(-half_logdet_r) * weighted_exp_sum(lhs, rhs, self.weights, engine=self.engine)  # ... x P
        num_out = out_mean.shape[-1]
        second = second[..., self.pair_of].unflatten(-1, (num_out, num_out))
        out_cov = second - out_mean[..., :, None] * out_mean[..., None, :]
        if self.with_model_variance:
            out_cov = out_cov + torch.diag_embed(self.signal_variance).to(out_cov)
        return MomentMatch(mean=out_mean, cov=symmetrize(out_cov), cross_cov=cov @ gain, gain=gain)
