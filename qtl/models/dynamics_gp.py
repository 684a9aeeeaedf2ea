"""The GP dynamics model: one GPyTorch ``ExactGP`` batched over the E output dimensions (Eq. 1-3)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import gpytorch
import torch
from gpytorch.constraints import GreaterThan
from gpytorch.priors import SmoothedBoxPrior
from linear_operator.utils.cholesky import psd_safe_cholesky
from torch import Tensor

from qtl.models.exact_settings import exact_gp_settings
from qtl.models.gp_checkpoint import GPCheckpoint
from qtl.models.gp_evidence import GPEvidence
from qtl.models.hyperparameters import GPHyperparameters
from qtl.models.point_noise import PointNoise, checked_extra_noise

# Hard floor on σ_ε² (absolute): keeps K + σ_ε²I factorisable whatever the data scale.
NOISE_VARIANCE_MIN = 1e-10
# A σ_ε² within this relative distance of the floor is the floor after rounding (e.g. exp(log σ²)):
# it is set just above the floor instead of being refused,
NOISE_FLOOR_RTOL = 1e-9
# at the floor × (1 + this): above GPyTorch's bound even where the bound is held in float32.
NOISE_FLOOR_MARGIN = 1e-6
# Soft floor on σ_ε² relative to the target variance: σ_ε² >= NOISE_TO_TARGET_MIN · var(Δ_e).
NOISE_TO_TARGET_MIN = 1e-8
# Bound on the signal-to-noise ratio α / σ_ε (PILCO's "curb"): 1/MAX_SNR <= α/σ_ε <= MAX_SNR.
MAX_SNR = 500.0
# Bound on ℓ_d relative to the spread of input d: std_d / MAX_LENGTHSCALE_RATIO <= ℓ_d <= ... · std_d.
MAX_LENGTHSCALE_RATIO = 100.0
# Width (in log units) of the Gaussian tails of the smoothed-box priors above.
PRIOR_TAIL_WIDTH = 0.05
# Spreads below this are treated as this (a constant input or output carries no scale).
MIN_DATA_STD = 1e-6
# Heuristic initial noise (PILCO): σ_ε² = var(Δ) / HEURISTIC_SNR², and at least the floor × HEURISTIC_FLOOR.
HEURISTIC_SNR = 10.0
HEURISTIC_FLOOR = 1 + NOISE_FLOOR_MARGIN
# Fewest training points a model accepts.
MIN_TRAIN_POINTS = 3
# Test inputs per GPyTorch prediction call in `predict`.
PREDICT_CHUNK = 1024


@dataclass(frozen=True)
class GPPosteriorCache:
    """What prediction at uncertain inputs needs of a fitted :class:`DynamicsGP`.

    ``inputs``: `n x D` training inputs; ``K_inv``: `E x n x n`, (K + σ_ε²I)⁻¹ per output;
    ``beta``: `E x n`, (K + σ_ε²I)⁻¹ y per output; ``hyperparameters``: θ. A sparse GP's cache has the same
    form at its m inducing inputs Z (``K_inv`` = K_mm⁻¹ − Σ⁻¹) and adds, for pathwise samples, ``prior_inv`` K_mm⁻¹
    and ``update_root`` R `E x m x m` with R Rᵀ = Σ⁻¹ (the covariance of q(u) mapped by K_mm⁻¹); None when exact.
    ``outputs``: the state dimensions the E outputs are, in order, of a ``state_dim``-D state (None: all of them,
    0..E−1, of an E-D state). ``constant_outputs``: state dimensions whose Δ is deterministic, ``constant_delta``
    `C` (:mod:`qtl.models.constant`).
    """

    inputs: Tensor
    K_inv: Tensor
    beta: Tensor
    hyperparameters: GPHyperparameters
    prior_inv: Tensor | None = None
    update_root: Tensor | None = None
    outputs: tuple[int, ...] | None = None
    state_dim: int | None = None
    constant_outputs: tuple[int, ...] = ()
    constant_delta: Tensor | None = None
    extra_noise: Tensor | None = None


def checked_outputs(
    outputs: Sequence[int] | None, num_outputs: int, state_dim: int | None = None, constant: Sequence[int] = ()
) -> tuple[tuple[int, ...], int]:
    """The state dimensions of ``num_outputs`` GP outputs and the state's dimension, checked.

    ``outputs`` default to 0..E−1; ``state_dim`` to E without ``outputs``, else to the largest output (or
    ``constant`` output) + 1. Outputs and constant outputs must be distinct dimensions below ``state_dim``, one per
    GP output (a ValueError otherwise).
    """
    found = tuple(range(num_outputs)) if outputs is None else tuple(int(d) for d in outputs)
    every = found + tuple(int(d) for d in constant)
    size = (num_outputs if outputs is None else max(every, default=-1) + 1) if state_dim is None else int(state_dim)
    if len(found) != num_outputs or len(set(every)) != len(every) or any(not 0 <= d < size for d in every):
        raise ValueError(f"outputs {list(found)} and constant outputs {list(constant)} must be distinct state "
                         f"dimensions in [0, {size}), one per GP output")
    return found, size


def _check_data(train_x: Tensor, train_y: Tensor) -> None:
    """Raise a ValueError naming the problem with a training set."""
    if not isinstance(train_x, Tensor) or not isinstance(train_y, Tensor):
        raise TypeError("train_x and train_y must be torch tensors")
    if train_x.dim() != 2:
        raise ValueError(f"train_x must be `n x D` (2-D), got shape {tuple(train_x.shape)}")
    if train_y.dim() != 2:
        raise ValueError(f"train_y must be `n x E` (2-D), got shape {tuple(train_y.shape)}")
    if train_x.shape[0] != train_y.shape[0]:
        raise ValueError(
            f"train_x has {train_x.shape[0]} rows but train_y has {train_y.shape[0]}: "
            "every input needs exactly one target"
        )
    if train_x.shape[0] < MIN_TRAIN_POINTS:
        raise ValueError(
            f"a DynamicsGP needs at least {MIN_TRAIN_POINTS} training points, got {train_x.shape[0]}"
        )
    if train_x.shape[1] < 1 or train_y.shape[1] < 1:
        raise ValueError(f"empty input or output dimension: D={train_x.shape[1]}, E={train_y.shape[1]}")
    for name, value in (("train_x", train_x), ("train_y", train_y)):
        bad = (~torch.isfinite(value)).sum().item()
        if bad:
            raise ValueError(f"{name} contains {bad} non-finite value(s) (NaN or inf)")


def _own_rows(extra_noise: Tensor | None, num_points: int) -> Tensor | slice:
    """The rows of tuples without extra noise (a target's own), when there are enough to centre priors on; else all."""
    if extra_noise is None:
        return slice(None)
    extra = torch.as_tensor(extra_noise)
    own = (extra == 0).reshape(num_points, -1).all(-1) if extra.numel() else torch.ones(num_points, dtype=torch.bool)
    return own if int(own.sum()) >= MIN_TRAIN_POINTS else slice(None)


class DynamicsGP(GPEvidence, GPCheckpoint, gpytorch.models.ExactGP):
    """Δ = x_{t+1} − x_t as E independent GPs in one batch (Eq. 1-3).

    Zero mean, ARD squared-exponential kernel ``ScaleKernel(RBFKernel)`` with signal variance
    α² and length-scales ℓ (Eq. 3), Gaussian likelihood with noise σ_ε², all with
    ``batch_shape = [E]``. Inputs are `n x D` (state features and action), targets `n x E`.

    Smoothed-box priors, centred on the spread of the data given at construction, keep
    evidence maximisation well conditioned: ℓ_d within a factor ``MAX_LENGTHSCALE_RATIO`` of
    std(x_d), α/σ_ε within ``MAX_SNR``, and σ_ε² above ``NOISE_TO_TARGET_MIN`` · var(Δ_e).

    ``outputs``: the state dimensions the E outputs model, in order (default: all, 0..E−1), of a ``state_dim``-D
    state (default: E without ``outputs``, else the largest output + 1); e.g. the velocities alone under speed
    integration (:mod:`qtl.propagation.integration`). ``constant_outputs``: state dimensions whose Δ the data
    showed constant, modelled as deterministic (Δ = ``constant_delta`` `C`, no variance; :mod:`qtl.models.constant`).
    The priors (and the heuristic θ) centre on the tuples without extra noise, the target's own.
    ``extra_noise``: c `n x E` (or `n`), tuple i of output e observed with noise σ_ε² + c_ei (c >= 0 fixed; source
    samples weighted by relevance, :mod:`qtl.models.point_noise`); None: σ_ε² for every tuple.
    """

    def __init__(
        self,
        train_x: Tensor,
        train_y: Tensor,
        hyperparameters: GPHyperparameters | None = None,
        *,
        outputs: Sequence[int] | None = None,
        state_dim: int | None = None,
        constant_outputs: Sequence[int] = (),
        constant_delta: Tensor | None = None,
        extra_noise: Tensor | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        _check_data(train_x, train_y)
        outputs, state_dim = checked_outputs(outputs, train_y.shape[1], state_dim, constant_outputs)
        constant_delta = torch.zeros(0) if constant_delta is None else torch.as_tensor(constant_delta).reshape(-1)
        if constant_delta.shape != (len(constant_outputs),) or not torch.isfinite(constant_delta).all():
            raise ValueError(f"constant_delta must be {len(constant_outputs)} finite values, one per constant output, "
                             f"got {constant_delta.tolist()}")
        train_x = train_x.to(dtype)
        train_y = train_y.to(dtype)
        num_outputs, input_dim = train_y.shape[1], train_x.shape[1]
        batch = torch.Size([num_outputs])
        likelihood = gpytorch.likelihoods.GaussianLikelihood(
            batch_shape=batch, noise_constraint=GreaterThan(NOISE_VARIANCE_MIN)
        )
        if extra_noise is not None:  # σ_ε² + c_ei at the training tuples: the same θ, the same parameter names
            extra = checked_extra_noise(extra_noise, train_x.shape[0], num_outputs).to(dtype=dtype,
                                                                                       device=train_x.device)
            likelihood.noise_covar = PointNoise(extra, batch_shape=batch,
                                                      noise_constraint=GreaterThan(NOISE_VARIANCE_MIN))
        # ExactGP keeps `E x n x D` inputs and `E x n` targets: one GP per output dimension.
        super().__init__(
            train_x.expand(num_outputs, *train_x.shape), train_y.T.contiguous(), likelihood
        )
        self.mean_module = gpytorch.means.ZeroMean(batch_shape=batch)
        self.covar_module = gpytorch.kernels.ScaleKernel(
            gpytorch.kernels.RBFKernel(ard_num_dims=input_dim, batch_shape=batch),
            batch_shape=batch,
        )
        self.outputs: tuple[int, ...] = outputs  # the state dimensions of the E outputs, in order
        self.state_dim = state_dim  # D of the state x whose Δ the outputs are
        self.constant_outputs = tuple(int(d) for d in constant_outputs)  # state dimensions of a deterministic Δ
        self.register_buffer("constant_delta", constant_delta.to(dtype=dtype, device=train_x.device))  # C
        own = _own_rows(extra_noise, train_x.shape[0])  # the priors centre on the target's own tuples
        self._register_data_priors(train_x[own], train_y[own])
        self.to(dtype=dtype, device=train_x.device)
        self.hyperparameters = (
            hyperparameters if hyperparameters is not None else self.heuristic_hyperparameters()
        )
        self.fit_objective: Tensor | None = None  # `E`: what the latest fit reached (None before any)

    # -- model -----------------------------------------------------------------------------

    def forward(self, x: Tensor) -> gpytorch.distributions.MultivariateNormal:
        """Prior of the latent Δ at `E x m x D` inputs."""
        return gpytorch.distributions.MultivariateNormal(self.mean_module(x), self.covar_module(x))

    def _register_data_priors(self, train_x: Tensor, train_y: Tensor) -> None:
        """Smoothed-box priors on log(ℓ/std x), log(α/σ_ε) and log(σ_ε²/var Δ)."""
        self.register_buffer("input_std", train_x.std(dim=0).clamp_min(MIN_DATA_STD))  # D
        self.register_buffer("target_var", train_y.var(dim=0).clamp_min(MIN_DATA_STD**2))  # E
        tail = PRIOR_TAIL_WIDTH
        ls_bound = math.log(MAX_LENGTHSCALE_RATIO)
        self.register_prior(
            "lengthscale_ratio_prior",
            SmoothedBoxPrior(-ls_bound, ls_bound, tail),
            lambda m: (m.scale_kernel.base_kernel.lengthscale.squeeze(-2) / m.input_std).log(),
        )
        snr_bound = math.log(MAX_SNR)
        self.register_prior(
            "snr_prior",
            SmoothedBoxPrior(-snr_bound, snr_bound, tail),
            # `E x 1`: one log-SNR per output dimension.
            lambda m: 0.5 * (m.scale_kernel.outputscale[:, None] / m.likelihood.noise).log(),
        )
        self.register_prior(
            "noise_floor_prior",
            SmoothedBoxPrior(math.log(NOISE_TO_TARGET_MIN), 0.0, tail),
            lambda m: (m.likelihood.noise / m.target_var[:, None]).log(),
        )

    # -- θ: the seam of transfer -----------------------------------------------------------

    @property
    def scale_kernel(self) -> gpytorch.kernels.ScaleKernel:
        """The kernel of Eq. 3, α² exp(−½ (x − x')ᵀ Λ⁻¹ (x − x')), batched over outputs."""
        return self.covar_module

    @property
    def num_outputs(self) -> int:
        """E, the number of output dimensions."""
        return self.train_targets.shape[0]

    @property
    def input_dim(self) -> int:
        """D, the GP input dimension."""
        return self.train_inputs[0].shape[-1]

    @property
    def train_x(self) -> Tensor:
        """Training inputs `n x D`."""
        return self.train_inputs[0][0]

    @property
    def train_y(self) -> Tensor:
        """Training targets `n x E`."""
        return self.train_targets.T

    @property
    def extra_noise(self) -> Tensor | None:
        """c `E x n`: σ_ε² + c_ei is the noise of tuple i of output e (None: σ_ε² for every tuple)."""
        noise = self.likelihood.noise_covar
        return noise.extra if isinstance(noise, PointNoise) else None

    def point_noise(self) -> Tensor:
        """The noise variance of every training tuple, σ_ε² s: `E x n`."""
        noise = self.likelihood.noise.detach()  # E x 1
        extra = self.extra_noise
        return noise.expand(-1, self.train_x.shape[0]) if extra is None else noise + extra

    def head(self, num_points: int) -> DynamicsGP:
        """The exact GP of the first ``num_points`` tuples (a target's own, ahead of source samples) at this θ."""
        exact = self.exact()
        extra = exact.extra_noise
        extra = None if extra is None or not bool(extra[:, :num_points].any()) else extra[:, :num_points].T
        return DynamicsGP(exact.train_x[:num_points], exact.train_y[:num_points], exact.hyperparameters,
                          outputs=exact.outputs, state_dim=exact.state_dim, constant_outputs=exact.constant_outputs,
                          constant_delta=exact.constant_delta, extra_noise=extra, dtype=exact.train_x.dtype)

    @property
    def hyperparameters(self) -> GPHyperparameters:
        """θ currently in the kernel and likelihood (detached copies)."""
        return GPHyperparameters(
            lengthscales=self.scale_kernel.base_kernel.lengthscale.detach().squeeze(-2).clone(),
            signal_variance=self.scale_kernel.outputscale.detach().clone(),
            noise_variance=self.likelihood.noise.detach().squeeze(-1).clone(),
        )

    @hyperparameters.setter
    def hyperparameters(self, theta: GPHyperparameters) -> None:
        expected = (self.num_outputs, self.input_dim)
        if (theta.num_outputs, theta.input_dim) != expected:
            raise ValueError(
                f"hyperparameters are for E={theta.num_outputs} outputs and D={theta.input_dim} "
                f"inputs, the model has E={expected[0]} and D={expected[1]}"
            )
        if (theta.noise_variance < NOISE_VARIANCE_MIN * (1 - NOISE_FLOOR_RTOL)).any():
            raise ValueError(
                f"noise_variance {theta.noise_variance.tolist()} is below the floor {NOISE_VARIANCE_MIN}"
            )
        theta = theta.to(dtype=self.train_x.dtype, device=self.train_x.device)
        noise = theta.noise_variance.clamp_min(NOISE_VARIANCE_MIN * (1 + NOISE_FLOOR_MARGIN))  # the floor, rounded
        self.scale_kernel.base_kernel.lengthscale = theta.lengthscales[:, None, :]
        self.scale_kernel.outputscale = theta.signal_variance
        self.likelihood.noise = noise[:, None]
        self.prediction_strategy = None  # θ changed: drop GPyTorch's cached solves

    def heuristic_hyperparameters(self) -> GPHyperparameters:
        """PILCO's initial θ: ℓ = std(x), α² = var(Δ), σ_ε² = α² / 100 (at least the noise floor)."""
        return GPHyperparameters(
            lengthscales=self.input_std.expand(self.num_outputs, -1).clone(),
            signal_variance=self.target_var.clone(),
            # Above the floor: a Δ of spread below HEURISTIC_SNR · √NOISE_VARIANCE_MIN would give less.
            noise_variance=(self.target_var / HEURISTIC_SNR**2).clamp_min(NOISE_VARIANCE_MIN * HEURISTIC_FLOOR),
        )

    # -- prediction --------------------------------------------------------------------------

    def predict(self, x: Tensor, *, include_noise: bool = False) -> tuple[Tensor, Tensor]:
        """Predictive mean and variance of Δ at deterministic inputs `m x D` (Eq. 1-2): `m x E` each."""
        if x.dim() != 2 or x.shape[-1] != self.input_dim:
            raise ValueError(f"x must be `m x {self.input_dim}`, got shape {tuple(x.shape)}")
        if not torch.isfinite(x).all():
            raise ValueError("x contains non-finite value(s) (NaN or inf)")
        self.eval()
        self.likelihood.eval()
        x = x.to(self.train_x)
        means, variances = [], []
        with torch.no_grad(), exact_gp_settings():
            # In chunks: GPyTorch forms the test-test covariance of each call, `m x m` per output.
            for chunk in x.split(PREDICT_CHUNK):
                dist = self(chunk.expand(self.num_outputs, *chunk.shape))
                if include_noise and self.extra_noise is not None:  # σ_ε² at a new input, whatever its count
                    means.append(dist.mean.T)
                    variances.append((dist.variance + self.likelihood.noise).T)
                    continue
                if include_noise:
                    dist = self.likelihood(dist)
                means.append(dist.mean.T)
                variances.append(dist.variance.T)
        return torch.cat(means), torch.cat(variances)

    def exact(self) -> DynamicsGP:
        """The exact GP of this data and θ: the model itself (a sparse model gives its exact twin)."""
        return self

    def posterior_cache(self) -> GPPosteriorCache:
        """(K + σ_ε²I)⁻¹ and β = (K + σ_ε²I)⁻¹y per output (σ_ε²I + C with per-point noise), at uncertain inputs."""
        theta = self.hyperparameters
        extra = self.extra_noise
        with torch.no_grad():
            K = self.covar_module(self.train_inputs[0]).to_dense()  # E x n x n
            if extra is None:
                K = K + theta.noise_variance[:, None, None] * torch.eye(
                    K.shape[-1], dtype=K.dtype, device=K.device
                )
            else:
                K = K + torch.diag_embed(theta.noise_variance[:, None] + extra)
            chol = psd_safe_cholesky(K)
            beta = torch.cholesky_solve(self.train_targets.unsqueeze(-1), chol).squeeze(-1)
            K_inv = torch.cholesky_inverse(chol)
        return GPPosteriorCache(inputs=self.train_x, K_inv=K_inv, beta=beta, hyperparameters=theta,
                                outputs=self.outputs, state_dim=self.state_dim,
                                constant_outputs=self.constant_outputs, constant_delta=self.constant_delta,
                                extra_noise=None if extra is None else extra.detach().clone())
