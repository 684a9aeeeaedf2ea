"""Long-term prediction by analytic moment matching through policy and GP (PILCO, Eq. 4).

One step from x_t ~ N(μ, Σ), as PILCO's ``propagate``: features y = φ(x) (exact, gTrig), the
action u = π(y) at the Gaussian N(E y, cov y) (exact moments, gp2 + gSat), the GP at the
Gaussian input [y, u] (exact moments, gp0), then x_{t+1} = x_t + Δ. The cross-covariances
cov[x, y], cov[x, u], cov[x, Δ] are chained through the gains Σ⁻¹ cov[·, ·] under the
approximation that each joint is Gaussian; the state distribution is thereby moment-matched to
a Gaussian at every step.

Output noise: the predicted Δ is the latent transition (PILCO gp0, "predictive variances
contain uncertainty about the function, but no noise"): σ_ε² is treated as measurement noise
of the training targets and is not propagated. ``include_noise=True`` adds diag(σ_ε²) to the
covariance of Δ at every step instead.

Integration (``integration``, :mod:`qtl.propagation.integration`): ``delta`` steps x_{t+1} = x_t + Δ in every
dimension; ``speed`` evaluates the GP on the E' modelled outputs only (all but the positions) and steps
x_{t+1} = x_t A + Δ J (positions by the trapezoid rule from their velocities), whose moments under the joint
Gaussian of (x_t, Δ) are exact: μ A + μ_Δ J and Aᵀ Σ A + Jᵀ Σ_Δ J + Aᵀ C J + (Aᵀ C J)ᵀ, C = cov[x_t, Δ].

Formulations (``engine.moments``, :class:`qtl.kernels.Engine`): ``reference`` symmetrizes each step's covariance;
``fused`` keeps it exactly symmetric by construction (the start's is symmetrized once) and skips
the input–output covariance of Δ, which the step does not use.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from qtl.constraints import SURVIVALS, Constraint, gaussian_return, terminating
from qtl.errors import UserError
from qtl.gaussian import Gaussian, GaussianMap, MomentMatch, batch_matmul, full_batch, symmetrize
from qtl.kernels import SEKernelMoments
from qtl.kernels.engine import DEFAULT_ENGINE, Engine
from qtl.policies.base import Policy
from qtl.propagation.base import DynamicsSource, Rollout
from qtl.propagation.gp_cache import propagation_inputs
from qtl.propagation.integration import INTEGRATION, DeltaIntegration, LinearIntegration, make_integration
from qtl.rewards import ExpectedSaturatingReward
from qtl.task import Kinematics


class MomentMatching:
    """Propagates Gaussian state distributions through a policy and a GP dynamics model (a :class:`Propagator`).

    ``model``: a :class:`~qtl.models.GPPosteriorCache` (or anything with ``posterior_cache()``),
    or a sequence of caches of equal sizes, stacked as a leading batch dimension `M` that
    broadcasts against the batch of the start distribution (and a batched policy's restarts `R`). GP inputs are
    [φ(x), u] (`D + K + F`), GP outputs Δ = x_{t+1} − x_t in raw coordinates of the state dimensions the model
    names (``outputs``: all D, or the modelled ones; deterministic ``constant_outputs`` go to the step's offset).
    ``policy``: acts on the features φ(x) (``prepare()`` gives its moment map).
    ``reward``: scores the successor states. ``angle_dims``: the dynamics' angle dimensions.
    ``dtype``: of the propagation (default: the cache's); the policy must share it, start
    distributions are converted. ``engine``: the code that computes every moment (features, policy,
    GP, reward; ``qtl.build`` resolves it from ``kernels.*``). ``integration``: ``delta`` (x + Δ), ``speed`` (the
    GP's modelled outputs only, positions integrated from their velocities; needs ``kinematics``: positions,
    velocities, period T) or a :class:`~qtl.propagation.integration.LinearIntegration` (its A, J and outputs).
    ``constraints``: the task's state bounds (:mod:`qtl.constraints`): the return weights each step by the
    survival S_t (terminate) and subtracts w (1 − p_t) (penalty), p_t from x_t's marginals. ``survival``: ``markov``
    (S_t from each consecutive pair's bivariate Gaussian, the lag-one covariance of the step) or ``product``
    (S_t = Π_{τ≤t} p_τ, Safe-PILCO's; :mod:`qtl.constraints`).
    """

    @staticmethod
    def check_settings(integration: str = "delta", survival: str = "markov", **_: object) -> None:
        """The settings, checked before any work (``qtl.build`` calls it): a UserError naming what to fix."""
        if integration not in INTEGRATION:
            raise UserError(f"propagation.integration must be one of {', '.join(INTEGRATION)}, got {integration!r}")
        if survival not in SURVIVALS:
            raise UserError(f"propagation.survival must be one of {', '.join(SURVIVALS)}, got {survival!r}")

    def __init__(
        self,
        model: DynamicsSource,
        policy: Policy,
        reward: ExpectedSaturatingReward,
        *,
        angle_dims: Sequence[int] = (),
        include_noise: bool = False,
        integration: str | LinearIntegration = "delta",
        kinematics: Kinematics | None = None,
        constraints: Sequence[Constraint] = (),
        survival: str = "markov",
        dtype: torch.dtype | None = None,
        engine: Engine = DEFAULT_ENGINE,
    ) -> None:
        self.check_settings(survival=survival)
        self.constraints = tuple(constraints)
        # The markov survival needs each step's lag-one covariance cov(x_t, x_{t+1}); nothing else does.
        self._lagged = survival == "markov" and bool(terminating(self.constraints))
        if isinstance(integration, str):
            self.check_settings(integration=integration)
            if integration == "speed" and kinematics is None:
                raise UserError("propagation.integration=speed needs the task's kinematics: add task.kinematics "
                                "(positions, velocities) or set propagation.integration=delta")
        data, self.features, self.dtype = propagation_inputs(model, policy, reward, angle_dims, dtype)
        self.engine = engine
        self.state_dim = self.features.state_dim
        # The step x_{t+1} = x_t + Δ, or x_t A + Δ J with the GP evaluated on the modelled outputs only.
        self.integration: DeltaIntegration | LinearIntegration = (
            make_integration(integration, self.state_dim, kinematics, self.dtype, data["beta"].device)
            if isinstance(integration, str) else integration
        )
        self.integration, data = self.integration.for_model(data)  # the model's outputs, checked
        self.policy = policy
        self.reward = reward
        self.include_noise = include_noise
        self.noise_variance = data["noise_variance"]  # ... x E (E': the modelled outputs)
        self._noise_cov = self.integration.covariance(self.noise_variance)  # diag(σ_ε²), or Jᵀ diag(σ_ε²) J
        # Everything that depends only on data and θ is computed here, once.
        self.dynamics = SEKernelMoments(
            data["inputs"], data["beta"], data["lengthscales"], data["signal_variance"], data["K_inv"], engine=engine
        )

    def _step(self, state: Gaussian, policy_map: GaussianMap) -> tuple[Gaussian, MomentMatch, Tensor | None]:
        """x_t ~ N(μ, Σ) ↦ (x_{t+1}, moments of u_t, cov(x_t, x_{t+1}) or None), as PILCO's ``propagate``.

        The fused step keeps Σ exactly symmetric. The lag-one covariance `... x D x D` only under the markov survival.
        """
        if not self.engine.fused:
            return self._reference_step(state.expand(), policy_map)
        state = full_batch(state)
        mean, cov = state.mean, state.cov
        feats = self.features.moments(state, self.engine)  # y = φ(x); cross_cov = cov[x, y]
        act = policy_map(feats.output)  # u = π(y); cross_cov = cov[y, u]
        gp_in = _joint_input(feats, act)
        delta_mean, delta_cov, delta_gain = self.dynamics.mean_cov_gain(gp_in)  # Δ; gain = cov[y u]⁻¹ cov[[y u], Δ]
        # cov[x, [y u]] = [cov[x, y], cov[x, y] Σ_y⁻¹ cov[y, u]], then cov[x, Δ] likewise.
        cov_x_in = torch.cat([feats.cross_cov, batch_matmul(feats.cross_cov, act.gain)], dim=-1)
        cov_x_delta = batch_matmul(cov_x_in, delta_gain)
        lag = self.integration.lag_covariance(cov, cov_x_delta) if self._lagged else None
        # The summands of x_{t+1}: x_t and Δ, or x_t A and Δ J (speed integration).
        mean, cov, delta_mean, delta_cov, cov_x_delta = self.integration.moment_terms(
            mean, cov, delta_mean, delta_cov, cov_x_delta)
        # Σ and cov Δ are exactly symmetric, and so is each sum below: no symmetrize needed.
        next_cov = (cov + delta_cov) + (cov_x_delta + cov_x_delta.mT)
        if self.include_noise:
            next_cov = next_cov + self._noise_cov
        return Gaussian(mean + delta_mean, next_cov), act, lag

    def _reference_step(self, state: Gaussian, policy_map: GaussianMap
                        ) -> tuple[Gaussian, MomentMatch, Tensor | None]:
        """:meth:`_step`, reference formulation: symmetrized after each step."""
        mean, cov = state.mean, state.cov
        feats = self.features.moments(state, self.engine)  # y = φ(x); cross_cov = cov[x, y]
        act = policy_map(feats.output)  # u = π(y); cross_cov = cov[y, u]
        gp_in = _joint_input(feats, act)
        delta = self.dynamics(gp_in)  # Δ; gain = cov[y u]⁻¹ cov[[y u], Δ]
        # cov[x, [y u]] = [cov[x, y], cov[x, y] Σ_y⁻¹ cov[y, u]], then cov[x, Δ] likewise.
        cov_x_in = torch.cat([feats.cross_cov, feats.cross_cov @ act.gain], dim=-1)
        cov_x_delta = cov_x_in @ delta.gain
        lag = self.integration.lag_covariance(cov, cov_x_delta) if self._lagged else None
        # The summands of x_{t+1}: x_t and Δ, or x_t A and Δ J (speed integration).
        mean, cov, delta_mean, delta_cov, cov_x_delta = self.integration.moment_terms(
            mean, cov, delta.mean, delta.cov, cov_x_delta)
        next_cov = cov + delta_cov + cov_x_delta + cov_x_delta.mT
        if self.include_noise:
            next_cov = next_cov + self._noise_cov
        return Gaussian(mean + delta_mean, symmetrize(next_cov)), act, lag

    def _with_policy_batch(self, state: Gaussian) -> Gaussian:
        """``state`` in the propagation's dtype, its batch broadcast against a batched policy's (`R`, restarts).

        The fused step needs an exactly symmetric Σ (it keeps it so): the start's is symmetrized.
        """
        state = state.to(dtype=self.dtype)
        if self.engine.fused:
            state = Gaussian(state.mean, symmetrize(state.cov))
        if not self.policy.batch_shape:
            return state
        batch = torch.broadcast_shapes(state.batch_shape, self.policy.batch_shape)
        return Gaussian(state.mean.expand(*batch, state.dim), state.cov.expand(*batch, state.dim, state.dim))

    def step(self, state: Gaussian) -> tuple[Gaussian, Gaussian]:
        """One step: the distribution of x_{t+1} and that of the action u_t."""
        next_state, action, _ = self._step(self._with_policy_batch(state), self.policy.prepare(self.engine))
        return next_state, action.output

    def rollout(self, start: Gaussian, horizon: int) -> Rollout:
        """H steps from N(μ_0, Σ_0); V = Σ_{t=1..H} E[r(x_t)] (Eq. 4), differentiable in ψ.

        With constraints V = Σ_t S_t (E[r(x_t)] − c_t) (:func:`qtl.constraints.gaussian_return`). A batched
        policy (ψ `R x ...`, restarts) gives R rollouts at once: ``value`` `R` and so on.
        """
        if start.dim != self.state_dim:
            raise ValueError(f"start must be a {self.state_dim}-D distribution, got {start.dim}-D")
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        start = self._with_policy_batch(start)
        policy_map = self.policy.prepare(self.engine)  # ψ-only quantities (β_π, ...) once per rollout
        states, actions, lags = [start], [], []
        state = start
        for _ in range(horizon):
            state, action, lag = self._step(state, policy_map)
            states.append(state)
            actions.append(action)
            lags.append(lag)
        trajectory = _stack_states(states)
        # The successors x_1..x_H are scored in one batched call, outside the recursion.
        successors = Gaussian(trajectory.mean[..., 1:, :], trajectory.cov[..., 1:, :, :])
        rewards = self.reward.expected(successors, self.engine)  # ... x H
        lag_cov = None
        if self._lagged:  # cov(x_{t−1}, x_t) `... x H x D x D`, broadcast as the states are
            batch = trajectory.mean.shape[:-2]
            lag_cov = torch.stack([lag.expand(*batch, *lag.shape[-2:]) for lag in lags], dim=-3)
        value, survival = (gaussian_return(self.constraints, rewards, successors, lag_cov) if self.constraints
                           else (rewards.sum(-1), None))
        return Rollout(
            value=value,
            rewards=rewards,
            states=trajectory,
            actions=_stack_states([a.output for a in actions]),
            survival=survival,
        )

    def expected_return(self, start: Gaussian, horizon: int) -> Tensor:
        """V^π(x_0) = Σ_{t=1..H} E[r(x_t)] (Eq. 4; with constraints, survival-weighted): `...`, differentiable in ψ."""
        return self.rollout(start, horizon).value


def _joint_input(feats: MomentMatch, act: MomentMatch) -> Gaussian:
    """The GP input [y, u] as one Gaussian: mean `... x (Y + F)`, covariance [[cov y, cov[y, u]], [·ᵀ, cov u]]."""
    return Gaussian(
        torch.cat([feats.mean, act.mean], dim=-1),
        torch.cat(
            [
                torch.cat([feats.cov, act.cross_cov], dim=-1),
                torch.cat([act.cross_cov.mT, act.cov], dim=-1),
            ],
            dim=-2,
        ),
    )


def _stack_states(states: Sequence[Gaussian]) -> Gaussian:
    """Stack per-step distributions along a new time dimension before the event dimension."""
    batch = torch.broadcast_shapes(*(s.batch_shape for s in states))
    dim = states[0].dim
    return Gaussian(
        torch.stack([s.mean.expand(*batch, dim) for s in states], dim=-2),
        torch.stack([s.cov.expand(*batch, dim, dim) for s in states], dim=-3),
    )
