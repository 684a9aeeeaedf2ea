"""A sparse GP dynamics model for large data: SGPR with m shared inducing inputs (Titsias 2009).

The same model as :class:`~qtl.models.DynamicsGP` (zero mean, the SE kernel of Eq. 3, Gaussian
noise, E outputs in one batch) with GPyTorch's ``InducingPointKernel``: evidence maximisation
uses Titsias' collapsed bound, O(n m²) per evaluation instead of O(n³) (evaluated with its gradient in
closed form by :mod:`qtl.models.collapsed_bound`), and optimises the m inducing inputs Z (shared by the
E outputs) together with θ. PILCO's own sparse option is FITC
with ~300 pseudo-inputs; SGPR has the same predictive form and a bound that does not overfit Z.

Prediction (Eq. 1-2 with the inducing inputs), per output a, with Σ = K_mm + σ⁻² K_mn K_nm:

    m(x) = k_xm β,        β = σ⁻² Σ⁻¹ K_mn y
    v(x) = α² − k_xm (K_mm⁻¹ − Σ⁻¹) k_mx

which is the exact GP's form with (Z, β, K_mm⁻¹ − Σ⁻¹) in place of (X, β, (K + σ²I)⁻¹): the
posterior cache has that form, so moment matching and particles run through it unchanged, at
O(m²) per step. With Z = X (and no jitter) the model is the exact GP.

Per-point noise (``extra_noise`` c, as :class:`~qtl.models.DynamicsGP`'s; :mod:`qtl.models.point_noise`): tuple i
observed with variance λ_i = σ² + c_i, Λ = diag(λ) in place of σ²I throughout: Σ = K_mm + K_mn Λ⁻¹ K_nm,
β = Σ⁻¹ K_mn Λ⁻¹ y, v(x) unchanged in form (the same cache), and the bound log N(y | 0, Q_nn + Λ) −
½ tr(Λ⁻¹ (K_nn − Q_nn)): the model of the rows scaled by λ_i^{-1/2} at unit noise (:mod:`qtl.models.collapsed_bound`).
A new input's noise is σ².

K_mm carries a fixed jitter δ = ``jitter`` · α² on its diagonal, in the bound and the prediction
alike (the inducing values u observed with variance δ). Without it, learned Z that crowd the
input space at the learned lengthscales make K_mm singular to working precision (eigenvalues
~1e-17 of α² on a fitted mountain car, m = 300), so K_mm⁻¹ − Σ⁻¹ reaches ~1e15 and the cached
variance cancels to noise (off by ~10⁴ σ_ε²). With δ = 1e-6 α², ‖K_mm⁻¹‖ <= 1e6 / α².
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Iterator, Sequence

import gpytorch
import torch
from linear_operator import to_dense
from linear_operator.utils.cholesky import psd_safe_cholesky
from linear_operator.utils.errors import NotPSDError
from torch import Tensor

from qtl import health
from qtl.models.collapsed_bound import collapsed_bound
from qtl.models.dynamics_gp import DynamicsGP, GPPosteriorCache
from qtl.models.exact_settings import EXACT_CHOLESKY_SIZE, exact_gp_settings
from qtl.models.gp_evidence import DEFAULT_MAX_ITER, DEFAULT_RESTARTS, RESTART_LOG_SCALE, WARM_RESTART_TOLERANCE
from qtl.models.hyperparameters import GPHyperparameters

log = logging.getLogger(__name__)

# Inducing inputs by default (PILCO's FITC uses about 300 pseudo-inputs).
DEFAULT_INDUCING = 300
# K_mm's diagonal jitter as a fraction of the signal variance α² (GPflow's default jitter is 1e-6 on unit-scale data).
DEFAULT_JITTER = 1e-6


def jittered_inducing_covariance(k_mm: Tensor, signal_variance: Tensor, jitter: float) -> Tensor:
    """K_mm + jitter · α² I per output: `E x m x m` from K_mm `E x m x m` and α² `E`."""
    if jitter == 0:
        return k_mm
    eye = torch.eye(k_mm.shape[-1], dtype=k_mm.dtype, device=k_mm.device)
    return k_mm + (jitter * signal_variance)[..., None, None] * eye


class JitteredInducingPointKernel(gpytorch.kernels.InducingPointKernel):
    """GPyTorch's SGPR kernel with K_mm + ``jitter`` · α² I in place of K_mm (its bound and predictions).

    The base kernel must be a ``ScaleKernel`` (α² is its outputscale, `E`).
    """

    def __init__(self, base_kernel: gpytorch.kernels.ScaleKernel, inducing_points: Tensor,
                 likelihood: gpytorch.likelihoods.Likelihood, *, jitter: float = DEFAULT_JITTER) -> None:
        if not jitter >= 0:
            raise ValueError(f"jitter must be >= 0, got {jitter}")
        super().__init__(base_kernel, inducing_points=inducing_points, likelihood=likelihood)
        self.jitter = float(jitter)

    @property
    def _inducing_mat(self) -> Tensor:
        if not self.training and hasattr(self, "_cached_kernel_mat"):
            return self._cached_kernel_mat
        k_mm = to_dense(self.base_kernel(self.inducing_points, self.inducing_points))
        res = jittered_inducing_covariance(k_mm, self.base_kernel.outputscale, self.jitter)
        if not self.training:
            self._cached_kernel_mat = res
        return res

    def __deepcopy__(self, memo: dict) -> JitteredInducingPointKernel:
        copied = super().__deepcopy__(memo)
        copied.jitter = self.jitter
        return copied


@contextlib.contextmanager
def _structured_settings() -> Iterator[None]:
    """Exact Cholesky solves, but GPyTorch's structured log-density (Woodbury) for the evidence."""
    with (
        gpytorch.settings.max_cholesky_size(EXACT_CHOLESKY_SIZE),
        gpytorch.settings.fast_computations(covar_root_decomposition=False, log_prob=True, solves=False),
        gpytorch.settings.fast_pred_var(False),
    ):
        yield


class SparseDynamicsGP(DynamicsGP):
    """Δ = x_{t+1} − x_t by SGPR with m inducing inputs shared by the E outputs (Eq. 1-3, sparse).

    ``inducing_points``: Z `m x D` (default: ``num_inducing`` training inputs drawn without
    replacement by ``generator``; all of them when n <= m); ``jitter``: δ / α² on K_mm's
    diagonal (0: none, the model of Titsias 2009 as written). Everything else as
    :class:`~qtl.models.DynamicsGP`: θ get/set, priors, per-point ``extra_noise``, fit, predict, posterior_cache.
    """

    def __init__(
        self,
        train_x: Tensor,
        train_y: Tensor,
        hyperparameters: GPHyperparameters | None = None,
        *,
        num_inducing: int = DEFAULT_INDUCING,
        inducing_points: Tensor | None = None,
        generator: torch.Generator | None = None,
        jitter: float = DEFAULT_JITTER,
        outputs: Sequence[int] | None = None,
        state_dim: int | None = None,
        constant_outputs: Sequence[int] = (),
        constant_delta: Tensor | None = None,
        extra_noise: Tensor | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__(train_x, train_y, hyperparameters, outputs=outputs, state_dim=state_dim,
                         constant_outputs=constant_outputs, constant_delta=constant_delta, extra_noise=extra_noise,
                         dtype=dtype)
        if inducing_points is None:
            if num_inducing < 1:
                raise ValueError(f"num_inducing must be >= 1, got {num_inducing}")
            n = self.train_x.shape[0]
            chosen = torch.randperm(n, generator=generator)[:num_inducing] if n > num_inducing else torch.arange(n)
            inducing_points = self.train_x[chosen.to(self.train_x.device)]
        if inducing_points.dim() != 2 or inducing_points.shape[-1] != self.input_dim:
            raise ValueError(f"inducing_points must be `m x {self.input_dim}`, got {tuple(inducing_points.shape)}")
        self.covar_module = JitteredInducingPointKernel(
            self.covar_module, inducing_points.to(self.train_x).clone(), self.likelihood, jitter=jitter
        )
        self.to(dtype=dtype, device=self.train_x.device)

    @property
    def scale_kernel(self) -> gpytorch.kernels.ScaleKernel:
        """The kernel of Eq. 3 inside the inducing-point kernel (before wrapping: the kernel itself)."""
        kernel = self.covar_module
        return kernel.base_kernel if isinstance(kernel, gpytorch.kernels.InducingPointKernel) else kernel

    @property
    def jitter(self) -> float:
        """δ / α²: K_mm's diagonal jitter as a fraction of the signal variance."""
        return self.covar_module.jitter

    def evidence_settings(self) -> contextlib.AbstractContextManager[None]:
        """GPyTorch's exact, structured evaluation of the collapsed bound in O(n m²) (:meth:`gpytorch_log_evidence`).

        GPyTorch's log-density of the low-rank-plus-diagonal covariance (Woodbury and the `m x m`
        capacitance Cholesky): the same value as the dense `n x n` Cholesky, which costs O(n³).
        """
        return _structured_settings()

    def log_evidence(self) -> Tensor:
        """Titsias' collapsed bound plus log priors, divided by n, per output `E`, with its gradient in closed form.

        The value of GPyTorch's marginal likelihood of this model (:meth:`gpytorch_log_evidence`) at about half
        its cost (:mod:`qtl.models.collapsed_bound`); with per-point noise σ² + c, the bound with Λ = σ²I + C.
        """
        kernel = self.scale_kernel
        bound = collapsed_bound(self.train_x, self.train_targets, self.covar_module.inducing_points,
                                kernel.base_kernel.lengthscale.squeeze(-2), kernel.outputscale,
                                self.likelihood.noise.squeeze(-1), self.jitter, self.extra_noise)
        return (bound + self.log_prior()) / self.train_x.shape[0]

    @property
    def inducing_points(self) -> Tensor:
        """Z `m x D`."""
        return self.covar_module.inducing_points.detach()

    def fit(
        self,
        *,
        restarts: int = DEFAULT_RESTARTS,
        max_iter: int = DEFAULT_MAX_ITER,
        generator: torch.Generator | None = None,
    ) -> Tensor:
        """Maximise the collapsed bound over θ and Z from the current θ and ``restarts − 1`` perturbations.

        Z is shared by the outputs, so the restart with the best total bound is kept whole (θ and Z).
        """
        if restarts < 1:
            raise ValueError(f"restarts must be >= 1, got {restarts}")
        start_theta, start_z = self.hyperparameters.log(), self.inducing_points.clone()
        best: tuple[float, Tensor, Tensor, Tensor] | None = None  # (total, log θ, Z, per-output values)
        for attempt in range(restarts):
            log_theta = start_theta
            if attempt > 0:
                noise = torch.randn(log_theta.shape, generator=generator, dtype=log_theta.dtype).to(log_theta.device)
                log_theta = log_theta + RESTART_LOG_SCALE * noise
            try:
                self.hyperparameters = GPHyperparameters.from_log(log_theta)
                with torch.no_grad():
                    self.covar_module.inducing_points.copy_(start_z)
                value = self._optimise(max_iter)
            except (NotPSDError, ValueError, RuntimeError) as err:
                health.count(health.GP_FIT_FAILED)
                log.info("sparse GP fit restart %d failed and is discarded: %s", attempt, err)
                continue
            total = float(value.sum())
            if math.isfinite(total) and (best is None or total > best[0]):
                best = (total, self.hyperparameters.log(), self.inducing_points.clone(), value)
        if best is None:
            raise RuntimeError("evidence maximisation of the sparse GP failed in every restart")
        self.hyperparameters = GPHyperparameters.from_log(best[1])
        with torch.no_grad():
            self.covar_module.inducing_points.copy_(best[2])
        self.fit_objective = best[3]
        return best[3]

    def fit_warm(
        self,
        start: GPHyperparameters,
        reference: Tensor,
        *,
        inducing: Tensor | None = None,
        restarts: int = DEFAULT_RESTARTS,
        max_iter: int = DEFAULT_MAX_ITER,
        generator: torch.Generator | None = None,
        tolerance: float = WARM_RESTART_TOLERANCE,
    ) -> Tensor:
        """The collapsed bound maximised from the previous θ_p (``start``) and Z (``inducing`` `m x D`, if it fits).

        Z is shared by the outputs, so the rule is on the total: when the warm bound per point,
        summed over outputs, is below ``reference`` `E` summed minus E · ``tolerance``, :meth:`fit`
        runs from the current θ and Z (the cold start) and the better of the two is kept whole.
        """
        cold_theta, cold_z = self.hyperparameters, self.inducing_points.clone()
        warm_z = inducing is not None and inducing.shape == cold_z.shape
        try:
            self.hyperparameters = start
            if warm_z:
                with torch.no_grad():
                    self.covar_module.inducing_points.copy_(inducing.to(cold_z))
            value = self._optimise(max_iter)
        except (NotPSDError, ValueError, RuntimeError) as err:
            health.count(health.GP_FIT_FAILED)
            log.info("warm-started sparse GP fit failed, refitted cold: %s", err)
            value = torch.full((self.num_outputs,), -math.inf, dtype=cold_z.dtype, device=cold_z.device)
        total, limit = float(value.sum()), float(reference.sum()) - self.num_outputs * tolerance
        if math.isfinite(total) and total >= limit:
            self.fit_objective = value
            return value
        log.info("warm sparse GP fit short of the previous bound (%.4f < %.4f per point): cold restarts", total, limit)
        warm = (total, self.hyperparameters.log(), self.inducing_points.clone(), value)
        self.hyperparameters = cold_theta
        with torch.no_grad():
            self.covar_module.inducing_points.copy_(cold_z)
        try:
            cold_value = self.fit(restarts=restarts, max_iter=max_iter, generator=generator)
        except RuntimeError:
            if not math.isfinite(total):
                raise
            cold_value = None
        if cold_value is None or (math.isfinite(total) and total > float(cold_value.sum())):
            self.hyperparameters = GPHyperparameters.from_log(warm[1])
            with torch.no_grad():
                self.covar_module.inducing_points.copy_(warm[2])
            self.fit_objective = warm[3]
            log.info("cold restarts: the warm sparse GP fit kept (%.4f >= %s per point)", total,
                     "a failed cold fit" if cold_value is None else f"{float(cold_value.sum()):.4f}")
        else:
            log.info("cold restarts: the cold sparse GP fit kept (%.4f > %.4f per point)",
                     float(cold_value.sum()), total)
        return self.fit_objective

    def _factors(self) -> tuple[Tensor, Tensor, Tensor]:
        """L_m (chol of K_mm + δI), A = L_m⁻¹ K_mn Λ^{-1/2} (Λ = σ²I, or σ²I + C) and L_B (chol of B = I + A Aᵀ)."""
        theta = self.hyperparameters
        z = self.inducing_points
        kernel = self.scale_kernel
        with torch.no_grad(), exact_gp_settings():
            k_mm = kernel(z.expand(self.num_outputs, *z.shape)).to_dense()  # E x m x m
            k_mm = jittered_inducing_covariance(k_mm, theta.signal_variance, self.jitter)
            k_mn = kernel(z.expand(self.num_outputs, *z.shape), self.train_inputs[0]).to_dense()  # E x m x n
            chol_m = psd_safe_cholesky(k_mm)
            a = torch.linalg.solve_triangular(chol_m, k_mn, upper=False)
            extra = self.extra_noise
            if extra is None:
                a = a / theta.noise_variance.sqrt()[:, None, None]
            else:  # Λ = σ²I + C: K_mn Λ⁻¹ K_nm = (L_m A)(L_m A)ᵀ with A's columns over √λ
                a = a * (theta.noise_variance[:, None] + extra).rsqrt()[:, None, :]
            eye = torch.eye(z.shape[0], dtype=a.dtype, device=a.device)
            chol_b = psd_safe_cholesky(eye + a @ a.mT)
        return chol_m, a, chol_b

    def posterior_cache(self) -> GPPosteriorCache:
        """Z, β = σ⁻² Σ⁻¹ K_mn y and K_mm⁻¹ − Σ⁻¹ per output: the exact GP's cache form at the inducing inputs.

        With per-point noise Λ = σ²I + C: Σ = K_mm + K_mn Λ⁻¹ K_nm and β = Σ⁻¹ K_mn Λ⁻¹ y (``extra_noise`` C `E x n`
        kept in the cache).
        """
        chol_m, a, chol_b = self._factors()
        extra = self.extra_noise
        noise_std = self.hyperparameters.noise_variance.sqrt()
        eye = torch.eye(a.shape[-2], dtype=a.dtype, device=a.device)
        with torch.no_grad():
            # Σ = L_m B L_mᵀ, so K_mm⁻¹ − Σ⁻¹ = L_m⁻ᵀ (I − B⁻¹) L_m⁻¹ (I − B⁻¹ is PSD: B >= I).
            b_inv = torch.cholesky_inverse(chol_b)
            middle = eye - b_inv
            left = torch.linalg.solve_triangular(chol_m.mT, middle, upper=True)  # L_m⁻ᵀ (I − B⁻¹)
            k_inv = torch.linalg.solve_triangular(chol_m.mT, left.mT, upper=True).mT
            k_inv = 0.5 * (k_inv + k_inv.mT)
            # β = σ⁻² Σ⁻¹ K_mn y = L_m⁻ᵀ B⁻¹ A y / σ (per point: Σ⁻¹ K_mn Λ⁻¹ y = L_m⁻ᵀ B⁻¹ A Λ^{-1/2} y).
            if extra is None:
                ay = (a @ self.train_targets[..., None]) / noise_std[:, None, None]  # E x m x 1
            else:
                point = self.hyperparameters.noise_variance[:, None] + extra  # E x n
                ay = a @ (self.train_targets * point.rsqrt())[..., None]
            beta = torch.linalg.solve_triangular(chol_m.mT, torch.cholesky_solve(ay, chol_b), upper=True)
            # Pathwise samples (Wilson et al. 2020, sparse form): f = f̃ + k(·, Z) K_mm⁻¹ (u − f̃(Z) − ε̃), u ~ q(u),
            # ε̃ ~ N(0, δI) the inducing values' jitter (K_mm here is K_mm + δI), i.e. v = β − K_mm⁻¹ f̃(Z) + R ξ with
            # R Rᵀ = K_mm⁻¹ S_u K_mm⁻¹ + δ K_mm⁻² = Σ⁻¹ + δ K_mm⁻² = L_m⁻ᵀ (B⁻¹ + δ L_m⁻¹ L_m⁻ᵀ) L_m⁻¹
            # (S_u = K_mm Σ⁻¹ K_mm, with per-point noise too: Σ and B then carry Λ⁻¹).
            # No jitter: R = L_m⁻ᵀ L_B⁻ᵀ; else R = L_m⁻ᵀ G, G Gᵀ = B⁻¹ + δ L_m⁻¹ L_m⁻ᵀ (eigenvalues in (0, 2]).
            prior_inv = torch.cholesky_inverse(chol_m)
            if self.jitter == 0:
                root = torch.linalg.solve_triangular(chol_b.mT, eye.expand_as(chol_b), upper=True)  # L_B⁻ᵀ
            else:
                chol_m_inv = torch.linalg.solve_triangular(chol_m, eye.expand_as(chol_m), upper=False)  # L_m⁻¹
                delta = (self.jitter * self.hyperparameters.signal_variance)[:, None, None]
                root = psd_safe_cholesky(b_inv + delta * (chol_m_inv @ chol_m_inv.mT))
            update_root = torch.linalg.solve_triangular(chol_m.mT, root, upper=True)
        return GPPosteriorCache(inputs=self.inducing_points, K_inv=k_inv, beta=beta.squeeze(-1),
                                hyperparameters=self.hyperparameters, prior_inv=0.5 * (prior_inv + prior_inv.mT),
                                update_root=update_root, outputs=self.outputs,
                                state_dim=self.state_dim, constant_outputs=self.constant_outputs,
                                constant_delta=self.constant_delta,
                                extra_noise=None if extra is None else extra.detach().clone())

    def predict(self, x: Tensor, *, include_noise: bool = False) -> tuple[Tensor, Tensor]:
        """Predictive mean and variance of Δ at deterministic inputs `k x D` (Eq. 1-2, sparse form): `k x E` each."""
        if x.dim() != 2 or x.shape[-1] != self.input_dim:
            raise ValueError(f"x must be `k x {self.input_dim}`, got shape {tuple(x.shape)}")
        if not torch.isfinite(x).all():
            raise ValueError("x contains non-finite value(s) (NaN or inf)")
        cache = self.posterior_cache()
        theta = cache.hyperparameters
        x = x.to(self.train_x)
        with torch.no_grad(), exact_gp_settings():
            z = cache.inputs.expand(self.num_outputs, *cache.inputs.shape)
            k_xm = self.scale_kernel(x.expand(self.num_outputs, *x.shape), z).to_dense()  # E x k x m
            mean = (k_xm @ cache.beta[..., None]).squeeze(-1)
            var = theta.signal_variance[:, None] - ((k_xm @ cache.K_inv) * k_xm).sum(-1)
            var = var.clamp_min(0.0)
            if include_noise:
                var = var + theta.noise_variance[:, None]
        return mean.T, var.T

    def exact(self) -> DynamicsGP:
        """The exact GP on the same data with the same θ and per-point noise (e.g. for leave-one-out predictions)."""
        extra = self.extra_noise
        return DynamicsGP(self.train_x, self.train_y, self.hyperparameters, outputs=self.outputs,
                          state_dim=self.state_dim, constant_outputs=self.constant_outputs,
                          constant_delta=self.constant_delta, extra_noise=None if extra is None else extra.T,
                          dtype=self.train_x.dtype)
