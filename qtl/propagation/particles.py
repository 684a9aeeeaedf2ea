"""Long-term prediction by particles: reparameterised samples through policy and GP (Eq. 4; MC-PILCO, PIPPS).

The propagator composes a sampler (:mod:`qtl.propagation.samplers`), a step (:mod:`qtl.propagation.integration`)
and an optional resampler (:mod:`qtl.propagation.resampling`), with common random numbers from
:mod:`qtl.propagation.noise`; the search scores the reward of :mod:`qtl.propagation.objective`. The docs' concepts
page on propagation ("Particles in detail") holds the maths.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from qtl.constraints import PARTICLE_TEMPERATURE, Constraint, particle_return
from qtl.errors import NonFiniteObjective, UserError
from qtl.gaussian import Gaussian, matrix_root, sample_moments
from qtl.kernels.engine import DEFAULT_ENGINE, Engine
from qtl.policies.base import Policy
from qtl.propagation.base import DynamicsSource, Rollout
from qtl.propagation.gp_cache import propagation_inputs
from qtl.propagation.integration import INTEGRATION, make_integration
from qtl.propagation.noise import BaseNoise, draw_base_noise
from qtl.propagation.objective import SearchReward, check_search_settings, objective_reward
from qtl.propagation.pathwise import MatheronPaths
from qtl.propagation.resampling import gaussian_resample
from qtl.propagation.samplers import GPTensors, MarginalSampler, PathwiseSampler
from qtl.rewards import AngleDistanceReward, ExpectedSaturatingReward, RewardMixture
from qtl.task import Kinematics

# Fewest particles: the per-step covariance needs two.
MIN_PARTICLES = 2
# How the GP is sampled: afresh at every step, or one function per particle for the whole rollout.
SAMPLING = ("marginal", "pathwise")
# Random Fourier features L per output of a pathwise function (Monte Carlo error of its kernel ~ 1/√L).
DEFAULT_NUM_FEATURES = 1024
# The dtypes a pathwise function may be evaluated in (float64: the propagation's own dtype, no cast).
PATH_DTYPES = {"float64": torch.float64, "float32": torch.float32}


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
    after every step, replace the particles by draws from their fitted Gaussian (PIPPS's GR; the
    resampler :func:`~qtl.propagation.resampling.gaussian_resample`). ``sampling``: ``marginal`` (a fresh GP draw
    every step) or ``pathwise`` (one function per particle for the rollout), with ``num_features``
    random Fourier features L per output (the sampler: :mod:`qtl.propagation.samplers`).
    ``reward_width_scale``, ``reward_task_weight``, ``search_cost`` and ``task_search_cost``: the search reward
    scored by :meth:`expected_return`, built once by :func:`~qtl.propagation.objective.objective_reward`;
    :meth:`rollout` (predictions, figures) scores the task's reward. ``integration``: ``delta`` (x + Δ in every
    dimension) or ``speed`` (positions follow their velocities), with ``kinematics`` (positions, velocities and
    period, e.g. a :class:`~qtl.task.Kinematics`) needed for ``speed`` (the step:
    :mod:`qtl.propagation.integration`). ``search_start_scale`` s: the search
    (:meth:`expected_return`) starts the particles from N(μ_0, s² Σ_0) instead of N(μ_0, Σ_0) (predictions keep
    the task's): a long rollout of a chaotic system amplifies the start's spread, and with it the variance of the
    reparameterised gradient (MC-PILCO's cart-pole starts with std 0.01; PILCO's task with 0.1).
    ``path_dtype``: ``float64`` (default) evaluates pathwise functions in the propagation's dtype, ``float32``
    in float32 and returns them in the propagation's. ``seed``: of the base noise. ``constraints``: the task's state
    bounds (:mod:`qtl.constraints`): a particle that leaves a terminate bound stops collecting reward from that step
    on, by the running product of a sigmoid of its signed distance to the bound over ``constraint_temperature`` τ
    (state units; 0: the hard indicator, no gradient); a penalty bound costs w (1 − indicator) per particle and step.
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
        check_search_settings(reward_width_scale, reward_task_weight, search_cost)
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
        constraints: Sequence[Constraint] = (),
        constraint_temperature: float = PARTICLE_TEMPERATURE,
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
        if not constraint_temperature >= 0:
            raise UserError(f"constraint_temperature must be >= 0 (0: the hard indicator), "
                            f"got {constraint_temperature}")
        self.constraints = tuple(constraints)
        self.constraint_temperature = float(constraint_temperature)
        self.reward = reward  # the task's: predictions and figures
        self.search_reward: ExpectedSaturatingReward | SearchReward = objective_reward(
            reward, reward_width_scale=reward_width_scale, reward_task_weight=reward_task_weight,
            search_cost=search_cost, task_search_cost=task_search_cost)  # the objective's: expected_return
        data, self.features, self.dtype = propagation_inputs(model, policy, reward, angle_dims, dtype)
        self.state_dim = self.features.state_dim
        self.policy = policy
        self.engine = engine  # the policy's and the pathwise functions' code (``qtl.build``: from kernels.*)
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

        # The parts: the step, the sampler and the resampler, built once.
        self.integration = make_integration(integration, self.state_dim, kinematics, self.dtype, data["beta"].device)
        self.integration, data = self.integration.for_model(data)  # the model's outputs, checked
        self.resample = gaussian_resample if self.gaussian_resampling else None

        # Everything that depends only on data and θ is computed here, once.
        self.model_batch_shape = data["beta"].shape[:-2]
        inv_ls = data["lengthscales"].reciprocal()  # ... x E x D_in
        self._inv_lengthscales = inv_ls[..., :, None, :]  # ... x E x 1 x D_in
        self._data = data["inputs"][..., None, :, :] * self._inv_lengthscales  # ... x E x n x D_in
        self._data_sq = self._data.square().sum(-1)  # ... x E x n
        self._beta = data["beta"]
        gp = GPTensors(self._data, self._data_sq, self._beta, data["K_inv"], data["signal_variance"],
                       data["noise_variance"], data.get("prior_inv"), data.get("update_root"), data.get("extra_noise"))
        # What the pathwise functions are evaluated with: float32 with path_dtype=float32 (else the propagation's).
        self._eval_dtype = torch.float32 if self.path_dtype == "float32" else self.dtype
        self.sampler: MarginalSampler | PathwiseSampler = MarginalSampler(gp, include_noise=include_noise)
        if self.sampling == "pathwise":
            self.sampler = PathwiseSampler(gp, include_noise=include_noise, seed=self.seed,
                                           num_particles=self.num_particles, num_features=self.num_features,
                                           dtype=self.dtype, eval_dtype=self._eval_dtype, engine=engine)
            self._path_data, self._path_data_sq, self._path_signal_variance = (
                self.sampler.path_data, self.sampler.path_data_sq, self.sampler.path_signal_variance)

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
            noise = draw_base_noise(self.seed, draw, (self.num_particles, self.state_dim), horizon,
                                    resampling=self.gaussian_resampling,
                                    like={"device": self._beta.device, "dtype": self.dtype})
            self._noise = (key, noise)
        return self._noise[1]

    def functions(self, draw: int | None = None) -> MatheronPaths:
        """The P pathwise functions per output of one draw (default: the latest); needs ``sampling="pathwise"``.

        Drawn and solved in the propagation's dtype, then kept in the evaluation's (float32 with
        ``path_dtype="float32"``, which also forms the prior sample at the data in float32).
        """
        if not isinstance(self.sampler, PathwiseSampler):
            raise ValueError(f"functions() needs sampling='pathwise', this propagator samples {self.sampling!r}")
        return self.sampler.functions(self.draw_index() if draw is None else draw)

    # -- propagation ----------------------------------------------------------------------------

    def trajectories(self, start: Gaussian, horizon: int, draw: int | None = None) -> tuple[Tensor, Tensor]:
        """Particle paths from N(μ_0, Σ_0): states `... x P x (H+1) x D` (x_0..x_H), actions `... x P x H x F`.

        ``draw``: the base noise to use (default: that of the latest evaluation).
        """
        states, actions, _ = self._paths(start, horizon, draw)
        return states, actions

    def _paths(self, start: Gaussian, horizon: int, draw: int | None) -> tuple[Tensor, Tensor, Gaussian | None]:
        """States, actions, and (``expected_reward``) each step's predictive `... x P x H x D` per particle."""
        if start.dim != self.state_dim:
            raise ValueError(f"start must be a {self.state_dim}-D distribution, got {start.dim}-D")
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        start = start.to(dtype=self.dtype)
        draw = self.draw_index() if draw is None else draw
        start_noise, step_noise, resampling_noise = self.base_noise(horizon, draw)
        sample = self.sampler.rollout(draw, self.integration.modelled(step_noise))
        batch = torch.broadcast_shapes(start.batch_shape, self.model_batch_shape, self.policy.batch_shape)
        x = start.mean[..., None, :] + start_noise @ matrix_root(start.cov).mT  # x_0 = μ_0 + L_0 ε_0
        x = x.expand(*batch, self.num_particles, self.state_dim)
        states, actions, means, variances = [x], [], [], []
        act = self.policy.actions(self.engine)  # ψ-only quantities once per rollout
        for t in range(horizon):
            y = self.features(x)  # ... x P x (D + K), exact per particle
            u = act(y)  # ... x P x F
            z = torch.cat([y, u], dim=-1)[..., None, :, :] * self._inv_lengthscales  # ... x E x P x D_in
            drawn = sample(z, t)  # the GP's step per particle, ... x P x E
            if self.expected_reward:
                means.append(self.integration.step(x, drawn.mean))
                variances.append(drawn.variance)
            x = self.integration.step(x, drawn.delta)
            if self.resample is not None:
                x = self.resample(x, resampling_noise[t])
            states.append(x)
            actions.append(u)
        predictive = None
        if self.expected_reward:
            mean = torch.stack(means, dim=-2)  # ... x P x H x D
            var = self.sampler.predictive_variance(variances, mean)
            predictive = Gaussian(mean, self.integration.covariance(var))
        return torch.stack(states, dim=-2), torch.stack(actions, dim=-2), predictive

    def rollout(
        self, start: Gaussian, horizon: int, draw: int | None = None,
        reward: ExpectedSaturatingReward | AngleDistanceReward | RewardMixture | SearchReward | None = None,
    ) -> Rollout:
        """H steps from N(μ_0, Σ_0); V = mean over particles of Σ_{t=1..H} r(x_t) (Eq. 4), or of Σ_t s_t (r_t − c_t).

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
        survival = None
        if self.constraints:  # per particle: its relaxed survival s_t and penalty cost c_t (qtl.constraints)
            per_path, survival = particle_return(self.constraints, per_particle, states[..., 1:, :],
                                                 self.constraint_temperature)
            value, survival = per_path.mean(-1), None if survival is None else survival.mean(-2)
        else:
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
            survival=survival,
        )

    def expected_return(self, start: Gaussian, horizon: int) -> Tensor:
        """V^π(x_0) ≈ (1/P) Σ_p Σ_{t=1..H} r(x_t^p) (Eq. 4), r the search reward: `...`, differentiable in ψ."""
        draw = self.draw_index(evaluation=self.calls)
        self.calls += 1
        if self.search_start_scale != 1.0:  # the search's start: the task's spread narrowed, its mean kept
            start = Gaussian(start.mean, start.cov * self.search_start_scale**2)
        return self.rollout(start, horizon, draw, self.search_reward).value
