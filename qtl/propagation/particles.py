"""Long-term prediction by particles: reparameterised samples through policy and GP (Eq. 4; MC-PILCO, PIPPS).

P particles x_0 = μ_0 + L_0 ε_0 (L_0 L_0ᵀ = Σ_0) go through the map the real system goes
through: the features y = φ(x) exactly per particle, the action u = π(y) (squashing included),
then Δ drawn from the GP's predictive distribution at [y, u] by the reparameterisation trick,
x_{t+1} = x_t + m(x_t) + √v(x_t) ∘ ε_{t+1}, with per output a the mean m_a = k_a β_a and the
variance v_a = α_a² − k_a (K_a + σ_ε²I)⁻¹ k_aᵀ (+ σ_ε² with ``include_noise``) (Eq. 1-2). The
expected return (Eq. 4) is the mean over particles of Σ_{t=1..H} r(x_t), differentiable in ψ.

Two ways to sample the GP (``sampling``):

- ``marginal`` (default): as in moment matching, the E outputs are independent and the GP function
  is drawn afresh at every step: there is no correlation of f across steps or particles. A step
  costs O(n²) per particle and output (the variance).
- ``pathwise``: each particle draws one function f_p per output for the whole rollout by
  Matheron's rule (:mod:`qtl.propagation.pathwise`; Wilson et al. 2020), a prior sample from L
  random Fourier features plus a data-fitted update, and steps x_{t+1} = x_t + f_p(x_t) (+ σ_ε ε_{t+1}
  with ``include_noise``: the observation noise, independent per step). The particle's function
  is the same along its path, the GP's own belief; a step costs O(n + L) per particle and output.
  With ``expected_reward`` the per-step predictive is N(x_{t−1} + f_p, diag σ_ε²) (or a point
  without noise): given the function, the noise is the step's only randomness.
  ``path_dtype="float32"`` evaluates the drawn functions in float32 within a float64 rollout: the
  functions (ω̃, b, the weights, and the update v, still solved in float64 and then cast; its prior sample
  at the data f̃_p(X), a well-conditioned cos and `n x L` by `L x P` product, is formed in float32) and the
  scaled data are kept in float32, each step casts z̃ down, and f and ∂f/∂z̃ come back as float64.
  This is safe because, once v is solved (the ill-conditioned part, (K + σ_ε²I)⁻¹), evaluating
  f_p(z̃) = Σ_l W_pl cos(ω̃_lᵀz̃ + b_l) + Σ_i k_i v_pi is well conditioned: each term carries a
  relative round-off of a few float32 ulp (~1e-7, times 1 + |ω̃ᵀz̃ + b|), far below the Monte Carlo
  error of the function itself, whose kernel comes from L random features (~1/√L, 0.06 at L = 256).
  A long rollout amplifies any per-step perturbation (a swing-up is chaotic): on the 50-step cart-pole
  (n = 250, P = 400) float32 moves ∂V/∂ψ by ~1e-2 relative (the float64 torch twin by ~3e-11), still
  ~10× below the spread between two draws of the functions (~0.14).

Speed integration (``integration="speed"``, MC-PILCO's speed-integration model; :mod:`qtl.propagation.integration`):
the GP's draws are used for every state dimension but the positions q (its outputs there are left unused), and a
position follows its velocity, q_{t+1} = q_t + T q̇_t + (T/2) Δq̇_t, so that a particle's position and velocity stay
consistent; ``kinematics`` (the task's positions, velocities and control period T) says which dimensions. The
base noise keeps its `... x D` layout and the modelled outputs read their own columns of it. With
``expected_reward`` the step's predictive is N(x A + m J, Jᵀ diag(v) J): the draws are linear in the state.

Variance control by common random numbers: the base noise, ε_0 `P x D` and ε_1..ε_H
`H x P x E`, is a deterministic function of (``seed``, draw index). With ``resample_every = 0``
the draw index never changes, so every evaluation in a policy search sees the same noise and
the objective is a deterministic function of ψ (what L-BFGS needs). With ``resample_every = k``
it advances every k calls of :meth:`Particles.expected_return`: fresh noise every k evaluations,
for stochastic optimisers (Adam). With pathwise sampling the draw also holds the functions' random
numbers (frequencies ω̃, phases b, weights w, update noise ε: a stream of their own), so a draw is
one set of P functions, used by every evaluation of that draw. The noise is shared across the
batch dimensions of the start distribution, of stacked models and of a batched policy's restarts
(ψ `R x ...`, whose ``forward`` takes `R x P x D`), so a batched rollout equals the per-item rollouts.

Gaussian resampling (PIPPS's "GR", Parmas et al. 2018): with ``gaussian_resampling`` the particles
are replaced after every step by P fresh draws x = m̂ + L̂ ε' from the Gaussian of their sample mean
m̂ and covariance Σ̂ = L̂ L̂ᵀ (reparameterised, so the gradient flows through m̂ and L̂). The GP
step is still sampled exactly per particle; only the state distribution handed to the next step is
moment-matched, as moment matching does, which keeps the reparameterisation gradient of a long
(chaotic) rollout from exploding. ε' `H x P x D` is a third stream of the same draw.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from qtl.errors import NonFiniteObjective, UserError
from qtl.gaussian import Gaussian, matrix_root, sample_moments
from qtl.kernels import gp_predictive
from qtl.kernels.engine import DEFAULT_ENGINE, Engine
from qtl.policies.base import Policy
from qtl.propagation.base import DynamicsSource, Rollout
from qtl.propagation.gp_cache import propagation_inputs
from qtl.propagation.integration import SpeedIntegration
from qtl.propagation.pathwise import MatheronPaths, draw_features, matheron_paths, path_values
from qtl.rewards import AngleDistanceReward, ExpectedSaturatingReward, RewardMixture
from qtl.task import Kinematics

# Fewest particles: the per-step covariance needs two.
MIN_PARTICLES = 2
# Predictive variances at or below this are propagated as exactly 0 (standard deviation 1e-15):
# √v has an infinite derivative at 0, and its clamped form keeps the gradient finite.
SQRT_VARIANCE_FLOOR = 1e-30
# The base noise is drawn in this dtype and then converted to the propagation's.
NOISE_DTYPE = torch.float64
# The stream of the Gaussian-resampling noise within a draw (the start and step noise use stream 0).
RESAMPLING_STREAM = 1
# The stream of the pathwise functions' random numbers within a draw.
PATHWISE_STREAM = 2
# How the GP is sampled: afresh at every step, or one function per particle for the whole rollout.
SAMPLING = ("marginal", "pathwise")
# Random Fourier features L per output of a pathwise function (Monte Carlo error of its kernel ~ 1/√L).
DEFAULT_NUM_FEATURES = 1024
# The dtypes a pathwise function may be evaluated in (float64: the propagation's own dtype, no cast).
PATH_DTYPES = {"float64": torch.float64, "float32": torch.float32}
# How a particle's state steps: x + Δ in every dimension, or positions integrated from their velocities.
INTEGRATION = ("delta", "speed")


class BaseNoise(NamedTuple):
    """One draw of base noise: ε_0 `P x D`, ε_1..ε_H `H x P x E`, and ε'_1..ε'_H `H x P x D` (or None)."""

    start: Tensor
    steps: Tensor
    resampling: Tensor | None


def _safe_sqrt(var: Tensor) -> Tensor:
    """√v elementwise for v >= 0, exactly 0 with a zero (not NaN) gradient where v <= the floor."""
    positive = var > SQRT_VARIANCE_FLOOR
    return torch.where(positive, var.clamp_min(SQRT_VARIANCE_FLOOR).sqrt(), torch.zeros_like(var))


def _gaussian_resample(x: Tensor, noise: Tensor) -> Tensor:
    """P draws m̂ + L̂ ε' from the Gaussian fitted to particles ``x`` `... x P x D`; ``noise`` ε' `P x D`."""
    fitted = sample_moments(x)  # mean `... x D`, cov `... x D x D`
    return fitted.mean[..., None, :] + noise @ matrix_root(fitted.cov).mT


def _per_step_noise(gen: torch.Generator, shape: tuple[int, int], horizon: int) -> Tensor:
    """``horizon`` standard normal draws of ``shape``, one per step in order: `H x ...` (float64)."""
    return torch.stack([torch.randn(shape, generator=gen, dtype=NOISE_DTYPE) for _ in range(horizon)])


def _draw_seed(seed: int, draw: int, stream: int = 0) -> int:
    """A 32-bit seed for one stream of the base noise of one draw."""
    entropy = [seed, draw, stream] if stream else [seed, draw]  # stream 0 keeps the original seeds
    return int(np.random.SeedSequence(entropy).generate_state(1)[0])


SEARCH_COSTS = ("widened", "task", "auto")


def search_reward(
    reward: ExpectedSaturatingReward,
    width_scale: float = 1.0,
    task_weight: float = 0.0,
    cost: AngleDistanceReward | None = None,
) -> ExpectedSaturatingReward | AngleDistanceReward | RewardMixture:
    """The reward a particle search scores: (1 − w) × base + w × the task's reward.

    The base is ``cost`` (the task's declared search cost) when given, else the task's reward widened
    by ``width_scale``.
    """
    if task_weight == 1.0 or (cost is None and width_scale == 1.0):
        return reward
    base = cost if cost is not None else reward.widened(width_scale)
    return base if task_weight == 0.0 else RewardMixture([base, reward], [1.0 - task_weight, task_weight])


class Particles:
    """Propagates P reparameterised particles through a policy and a GP dynamics model (Eq. 4).

    The same interface as :class:`~qtl.propagation.MomentMatching`: ``model`` is a
    :class:`~qtl.models.GPPosteriorCache` (or anything with ``posterior_cache()``), or a sequence
    of caches of equal sizes stacked as a leading batch dimension `M` that broadcasts against
    the batch of the start distribution; ``policy`` acts on the features φ(x) (plain tensors,
    squashing included); ``reward`` scores the successor states per particle; ``angle_dims``:
    the dynamics' angle dimensions. ``num_particles``: P. ``resample_every``: fresh base noise
    every this many calls of :meth:`expected_return` (0: never — a deterministic objective).
    ``include_noise``: add σ_ε² to the predictive variance of Δ (default; without it Δ is drawn
    from the latent GP, as :class:`~qtl.propagation.MomentMatching` does by default).
    ``expected_reward``: score each step by E[r(x_t) | x_{t−1}], the expected reward under the
    particle's Gaussian predictive N(x_{t−1} + m, diag v), instead of r at the drawn x_t — the same
    expectation (Rao-Blackwellised; exact without angle dimensions, PILCO's moment-matched augmented
    state with them), smooth in ψ where the drawn particles all score ~0. ``gaussian_resampling``:
    after every step, replace the particles by draws from their fitted Gaussian (PIPPS's GR; see
    the module docstring). ``sampling``: ``marginal`` (a fresh GP draw every step) or ``pathwise``
    (one function per particle for the rollout; see the module docstring), with ``num_features``
    random Fourier features L per output. ``reward_width_scale``: the search scores the task's reward
    with its width × this (MC-PILCO's wider cost; 1: the task's own) in :meth:`expected_return`,
    mixed with ``reward_task_weight`` × the task's own (0: the widened alone; see :func:`search_reward`);
    ``search_cost``: ``widened`` (that), ``task`` (the task's declared angle/position cost
    ``task_search_cost`` in place of the widened reward, e.g. MC-PILCO's cart-pole cost) or ``auto``
    (the task's when it declares one, else widened); ``integration``: ``delta`` (x + Δ in every dimension) or
    ``speed`` (positions follow their velocities; see the module docstring), with ``kinematics`` (positions,
    velocities and period, e.g. a :class:`~qtl.task.Kinematics`) needed for ``speed``;
    :meth:`rollout` (predictions, figures) scores the task's reward. ``search_start_scale`` s: the search
    (:meth:`expected_return`) starts the particles from N(μ_0, s² Σ_0) instead of N(μ_0, Σ_0) (predictions keep
    the task's): a long rollout of a chaotic system amplifies the start's spread, and with it the variance of the
    reparameterised gradient (MC-PILCO's cart-pole starts with std 0.01; PILCO's task with 0.1).
    ``path_dtype``: ``float64`` (default) evaluates pathwise functions in the propagation's dtype, ``float32``
    in float32 and returns them in the propagation's (see the module docstring). ``seed``: of the base noise.
    ``dtype``: of the propagation (default: the cache's); the policy must share it. ``engine``: the code of the
    policy's actions, the pathwise functions and expected rewards (``qtl.build`` resolves it from ``kernels.*``).
    """

    @staticmethod
    def check_settings(
        num_particles: int = MIN_PARTICLES,
        resample_every: int = 0,
        seed: int = 0,
        sampling: str = "marginal",
        num_features: int = DEFAULT_NUM_FEATURES,
        reward_width_scale: float = 1.0,
        reward_task_weight: float = 0.0,
        search_cost: str = "widened",
        path_dtype: str = "float64",
        integration: str = "delta",
        search_start_scale: float = 1.0,
        **_: object,
    ) -> None:
        """The settings' ranges, checked before any work (``qtl.build`` calls it): a UserError naming what to fix."""
        if num_particles < MIN_PARTICLES:
            raise UserError(f"num_particles must be >= {MIN_PARTICLES}, got {num_particles}")
        if resample_every < 0:
            raise UserError(f"resample_every must be >= 0 (0: never resample), got {resample_every}")
        if seed < 0:
            raise UserError(f"seed must be >= 0, got {seed}")
        if sampling not in SAMPLING:
            raise UserError(f"propagation.sampling must be one of {', '.join(SAMPLING)}, got {sampling!r}")
        if num_features < 1:
            raise UserError(f"propagation.num_features must be >= 1 (random Fourier features), got {num_features}")
        if not reward_width_scale > 0:
            raise UserError(
                f"propagation.reward_width_scale must be > 0 (1: the task's reward), got {reward_width_scale}"
            )
        if not 0.0 <= reward_task_weight <= 1.0:
            raise UserError(
                f"propagation.reward_task_weight must be in [0, 1] (the task's reward's share of the search reward), "
                f"got {reward_task_weight}"
            )
        if search_cost not in SEARCH_COSTS:
            raise UserError(f"propagation.search_cost must be one of {', '.join(SEARCH_COSTS)}, got {search_cost!r}")
        if path_dtype not in PATH_DTYPES:
            raise UserError(f"propagation.path_dtype must be one of {', '.join(PATH_DTYPES)}, got {path_dtype!r}")
        if integration not in INTEGRATION:
            raise UserError(f"propagation.integration must be one of {', '.join(INTEGRATION)}, got {integration!r}")
        if not 0.0 < search_start_scale <= 1.0:
            raise UserError(f"propagation.search_start_scale must be in (0, 1] (1: the task's start spread), "
                            f"got {search_start_scale}")

    def __init__(
        self,
        model: DynamicsSource,
        policy: Policy,
        reward: ExpectedSaturatingReward,
        *,
        angle_dims: Sequence[int] = (),
        num_particles: int = 400,
        resample_every: int = 0,
        include_noise: bool = True,
        expected_reward: bool = False,
        gaussian_resampling: bool = False,
        sampling: str = "marginal",
        num_features: int = DEFAULT_NUM_FEATURES,
        reward_width_scale: float = 1.0,
        reward_task_weight: float = 0.0,
        search_cost: str = "widened",
        task_search_cost: AngleDistanceReward | None = None,
        path_dtype: str = "float64",
        integration: str = "delta",
        kinematics: Kinematics | None = None,
        search_start_scale: float = 1.0,
        seed: int = 0,
        dtype: torch.dtype | None = None,
        engine: Engine = DEFAULT_ENGINE,
    ) -> None:
        self.check_settings(num_particles=num_particles, resample_every=resample_every, seed=seed,
                            sampling=sampling, num_features=num_features, reward_width_scale=reward_width_scale,
                            reward_task_weight=reward_task_weight, search_cost=search_cost, path_dtype=path_dtype,
                            integration=integration, search_start_scale=search_start_scale)
        if integration == "speed" and kinematics is None:
            raise UserError("propagation.integration=speed needs the task's kinematics: add task.kinematics "
                            "(positions, velocities) or set propagation.integration=delta")
        if search_cost == "task" and task_search_cost is None:
            raise UserError("propagation.search_cost=task, but the task declares no search_reward: add "
                            "task.search_reward or set propagation.search_cost=widened (or auto)")
        data, self.features, self.dtype = propagation_inputs(model, policy, reward, angle_dims, dtype)
        self.state_dim = self.features.state_dim
        self.policy = policy
        self.engine = engine  # the policy's and the pathwise functions' code (``qtl.build``: from kernels.*)
        self.reward = reward  # the task's: predictions and figures
        cost = None if search_cost == "widened" else task_search_cost
        self.search_reward = search_reward(reward, reward_width_scale, reward_task_weight, cost)
        self.num_particles = int(num_particles)
        self.search_start_scale = float(search_start_scale)
        self.resample_every = int(resample_every)
        self.include_noise = include_noise
        self.expected_reward = bool(expected_reward)
        self.gaussian_resampling = bool(gaussian_resampling)
        self.sampling = str(sampling)
        self.num_features = int(num_features)
        self.path_dtype = str(path_dtype)
        self.seed = int(seed)
        self.calls = 0  # evaluations of expected_return so far: they set the draw index
        self._noise: tuple[tuple[int, int], BaseNoise] | None = None
        self._functions: tuple[int, MatheronPaths] | None = None

        self.integration: SpeedIntegration | None = None
        if integration == "speed":
            self.integration = SpeedIntegration(self.state_dim, kinematics, self.dtype, data["beta"].device)
            data = _select_outputs(data, self.integration.outputs)

        # Everything that depends only on data and θ is computed here, once.
        self.model_batch_shape = data["beta"].shape[:-2]
        inv_ls = data["lengthscales"].reciprocal()  # ... x E x D_in
        self._inv_lengthscales = inv_ls[..., :, None, :]  # ... x E x 1 x D_in
        self._data = data["inputs"][..., None, :, :] * self._inv_lengthscales  # ... x E x n x D_in
        self._data_sq = self._data.square().sum(-1)  # ... x E x n
        self._beta = data["beta"]
        self._K_inv = data["K_inv"]
        self._prior_inv, self._update_root = data.get("prior_inv"), data.get("update_root")  # a sparse GP's
        self._signal_variance = data["signal_variance"]
        self._noise_variance = data["noise_variance"]  # ... x E
        self._noise_std = self._noise_variance.sqrt()  # σ_ε: ... x E
        # What the pathwise functions are evaluated with: float32 copies with path_dtype=float32 (else these).
        self._eval_dtype = torch.float32 if self.path_dtype == "float32" else self.dtype
        self._path_data, self._path_data_sq, self._path_signal_variance = (
            t.to(self._eval_dtype) for t in (self._data, self._data_sq, self._signal_variance)
        )

    # -- common random numbers ------------------------------------------------------------------

    def draw_index(self, *, evaluation: int | None = None) -> int:
        """The draw of base noise that evaluation number ``evaluation`` (default: the latest) uses."""
        if evaluation is None:
            evaluation = max(self.calls - 1, 0)
        return evaluation // self.resample_every if self.resample_every else 0

    def base_noise(self, horizon: int, draw: int | None = None) -> BaseNoise:
        """ε_0 (start), ε_1..ε_H (steps) and, with Gaussian resampling, ε'_1..ε'_H of one draw (default: the latest)."""
        draw = self.draw_index() if draw is None else draw
        key = (draw, horizon)
        if self._noise is None or self._noise[0] != key:
            gen = torch.Generator().manual_seed(_draw_seed(self.seed, draw))
            shape = (self.num_particles, self.state_dim)
            # Drawn in float64 whatever the dtype, so that every dtype sees the same numbers; one
            # draw per step, in order, so that the noise of step t does not depend on the horizon.
            start = torch.randn(shape, generator=gen, dtype=NOISE_DTYPE)
            steps = _per_step_noise(gen, shape, horizon)
            resampling = None
            if self.gaussian_resampling:
                gen = torch.Generator().manual_seed(_draw_seed(self.seed, draw, RESAMPLING_STREAM))
                resampling = _per_step_noise(gen, shape, horizon)
            like = {"device": self._beta.device, "dtype": self.dtype}
            self._noise = (key, BaseNoise(start.to(**like), steps.to(**like),
                                          None if resampling is None else resampling.to(**like)))
        return self._noise[1]

    def functions(self, draw: int | None = None) -> MatheronPaths:
        """The P pathwise functions per output of one draw (default: the latest); needs ``sampling="pathwise"``.

        Drawn and solved in the propagation's dtype, then kept in the evaluation's (float32 with
        ``path_dtype="float32"``, which also forms the prior sample at the data in float32).
        """
        if self.sampling != "pathwise":
            raise ValueError(f"functions() needs sampling='pathwise', this propagator samples {self.sampling!r}")
        draw = self.draw_index() if draw is None else draw
        if self._functions is None or self._functions[0] != draw:
            gen = torch.Generator().manual_seed(_draw_seed(self.seed, draw, PATHWISE_STREAM))
            num_outputs, num_points, input_dim = self._data.shape[-3:]
            features = draw_features(gen, num_outputs, input_dim, num_points, self.num_particles, self.num_features)
            paths = matheron_paths(features, self._data, self._beta, self._K_inv, self._signal_variance,
                                   self._noise_variance, dtype=self._eval_dtype, prior_inv=self._prior_inv,
                                   update_root=self._update_root)
            self._functions = (draw, paths)
        return self._functions[1]

    # -- propagation ----------------------------------------------------------------------------

    def trajectories(self, start: Gaussian, horizon: int, draw: int | None = None) -> tuple[Tensor, Tensor]:
        """Particle paths from N(μ_0, Σ_0): states `... x P x (H+1) x D` (x_0..x_H), actions `... x P x H x F`.

        ``draw``: the base noise to use (default: that of the latest evaluation).
        """
        states, actions, _ = self._paths(start, horizon, draw)
        return states, actions

    def _paths(self, start: Gaussian, horizon: int, draw: int | None) -> tuple[Tensor, Tensor, Gaussian]:
        """States, actions, and each step's predictive N(x_{t−1} + m, diag v) `... x P x H x D` per particle."""
        if start.dim != self.state_dim:
            raise ValueError(f"start must be a {self.state_dim}-D distribution, got {start.dim}-D")
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        start = start.to(dtype=self.dtype)
        draw = self.draw_index() if draw is None else draw
        start_noise, step_noise, resampling_noise = self.base_noise(horizon, draw)
        if self.integration is not None:  # the modelled outputs read their own columns of the `... x D` noise
            step_noise = step_noise[..., list(self.integration.outputs)]
        functions = self.functions(draw) if self.sampling == "pathwise" else None
        batch = torch.broadcast_shapes(start.batch_shape, self.model_batch_shape, self.policy.batch_shape)
        x = start.mean[..., None, :] + start_noise @ matrix_root(start.cov).mT  # x_0 = μ_0 + L_0 ε_0
        x = x.expand(*batch, self.num_particles, self.state_dim)
        states, actions, means, variances = [x], [], [], []
        # Pathwise: the step noise σ_ε ε_t of every step in one product, `H x ... x P x E` (none without noise).
        noise_steps = None
        if functions is not None and self.include_noise:
            noise_steps = self._noise_std[..., None, :] * step_noise.view(
                horizon, *(1,) * (self._noise_std.dim() - 1), *step_noise.shape[1:])
        act = self.policy.actions(self.engine)  # ψ-only quantities once per rollout
        for t in range(horizon):
            y = self.features(x)  # ... x P x (D + K), exact per particle
            u = act(y)  # ... x P x F
            z = torch.cat([y, u], dim=-1)[..., None, :, :] * self._inv_lengthscales  # ... x E x P x D_in
            if functions is None:
                mean, var = gp_predictive(z, self._data, self._data_sq, self._beta, self._K_inv,
                                          self._signal_variance)  # ... x E x P (Eq. 1-2)
                var = var.clamp_min(0.0)  # round-off can make the latent variance slightly negative
                if self.include_noise:
                    var = var + self._noise_variance[..., None]
                delta = mean + _safe_sqrt(var) * step_noise[t].mT  # Δ ~ N(m, v) reparameterised
                if self.expected_reward:
                    means.append(self._step(x, mean.mT))
                    variances.append(var.mT)
                x = self._step(x, delta.mT)
            else:
                step = path_values(z.to(self._eval_dtype), self._path_data, self._path_data_sq,
                                   self._path_signal_variance, functions, self.engine)
                step = step.to(self.dtype).mT  # f_p: ... x P x E
                if self.expected_reward:
                    means.append(self._step(x, step))
                if noise_steps is not None:  # the observation noise, independent per step, on top of f_p
                    step = step + noise_steps[t]
                x = self._step(x, step)
            if resampling_noise is not None:
                x = _gaussian_resample(x, resampling_noise[t])
            states.append(x)
            actions.append(u)
        predictive = None
        if self.expected_reward:
            mean = torch.stack(means, dim=-2)  # ... x P x H x D
            if functions is None:
                var = torch.stack(variances, dim=-2)
            else:  # given its function a particle's step varies by the noise alone: σ_ε² (or 0) at every step
                var = (self._noise_variance if self.include_noise else torch.zeros_like(self._noise_variance))
                var = var[..., None, None, :].expand(*mean.shape[:-1], var.shape[-1])
            cov = torch.diag_embed(var) if self.integration is None else self.integration.covariance(var)
            predictive = Gaussian(mean, cov)
        return torch.stack(states, dim=-2), torch.stack(actions, dim=-2), predictive

    def _step(self, x: Tensor, delta: Tensor) -> Tensor:
        """x_{t+1} `... x P x D` from x_t and the GP's draws Δ of the modelled outputs `... x P x E`."""
        return x + delta if self.integration is None else self.integration.step(x, delta)

    def rollout(
        self, start: Gaussian, horizon: int, draw: int | None = None,
        reward: ExpectedSaturatingReward | AngleDistanceReward | RewardMixture | None = None,
    ) -> Rollout:
        """H steps from N(μ_0, Σ_0); V = mean over particles of Σ_{t=1..H} r(x_t) (Eq. 4).

        ``states`` and ``actions`` are the particles' per-step sample means and (unbiased)
        covariances. Uses the base noise of the latest evaluation unless ``draw`` is given, and
        does not count as an evaluation; r is the task's reward unless ``reward`` is given. A
        non-finite V raises :class:`~qtl.errors.NonFiniteObjective`.
        """
        reward = reward or self.reward
        states, actions, predictive = self._paths(start, horizon, draw)
        if self.expected_reward:
            per_particle = reward.expected(predictive, self.engine)  # ... x P x H, E[r(x_t) | x_{t−1}]
        else:
            per_particle = reward(states[..., 1:, :])  # ... x P x H, successor states x_1..x_H
        value = per_particle.sum(-1).mean(-1)
        if not torch.isfinite(value).all():
            finite = torch.isfinite(states).all(-1).flatten(end_dim=-2).all(0)  # H+1
            first = int((~finite).nonzero()[0, 0]) if not finite.all() else None
            bad = int((~torch.isfinite(per_particle.sum(-1))).sum())
            raise NonFiniteObjective(
                f"particle rollout: expected return {value.detach().flatten().tolist()} is not finite; "
                f"{bad} of {per_particle[..., 0].numel()} particle returns are not finite"
                + (f", the first non-finite state at step {first}" if first is not None else "")
            )
        return Rollout(
            value=value,
            rewards=per_particle.mean(-2),
            states=sample_moments(states, dim=-3),
            actions=sample_moments(actions, dim=-3),
        )

    def expected_return(self, start: Gaussian, horizon: int) -> Tensor:
        """V^π(x_0) ≈ (1/P) Σ_p Σ_{t=1..H} r(x_t^p) (Eq. 4), r the search reward: `...`, differentiable in ψ."""
        draw = self.draw_index(evaluation=self.calls)
        self.calls += 1
        if self.search_start_scale != 1.0:  # the search's start: the task's spread narrowed, its mean kept
            start = Gaussian(start.mean, start.cov * self.search_start_scale**2)
        return self.rollout(start, horizon, draw, self.search_reward).value


def _select_outputs(data: dict[str, Tensor], outputs: Sequence[int]) -> dict[str, Tensor]:
    """The cache's per-output tensors of ``outputs`` only (the shared inputs `... x n x D_in` as they are)."""
    index = torch.tensor(list(outputs), dtype=torch.long, device=data["beta"].device)
    output_dim = {"K_inv": -3, "prior_inv": -3, "update_root": -3, "beta": -2, "lengthscales": -2,
                  "signal_variance": -1, "noise_variance": -1}
    return {k: v.index_select(output_dim[k], index) if k in output_dim else v for k, v in data.items()}
