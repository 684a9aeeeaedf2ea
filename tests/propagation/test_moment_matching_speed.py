"""Moment matching with speed integration: the GP on the modelled outputs, positions by the trapezoid rule, exact."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from qtl.build import build
from qtl.errors import UserError
from qtl.features import AngleFeatures
from qtl.gaussian import Gaussian
from qtl.kernels.engine import Engine
from qtl.kernels.native import build as native_build
from qtl.propagation import MomentMatching
from qtl.propagation.integration import LinearIntegration, SpeedIntegration
from qtl.task import Kinematics
from tests.helpers import gradcheck_value_wrt_policy_and_start, tiny_config
from tests.propagation.reference import joint_draws
from tests.propagation.test_integration import CARTPOLE, LONG_PERIOD, MODELLED, cartpole_parts, start, trapezoid

DTYPE = torch.float64
ENGINES = {
    "reference": Engine(moments="reference"),
    "fused": Engine(moments="fused"),
    "native": Engine(exp_sums="native", moments="native"),
}
# The compiled kernels and the torch formulations compute the same moments: round-off only.
ENGINE_RTOL = 1e-10


@pytest.fixture(scope="module", autouse=True)
def native_kernels() -> None:
    """The compiled kernels, built (or loaded from the cache) once."""
    native_build.build()


class Recording(LinearIntegration):
    """A linear step that keeps what the moment-matching step hands it: (μ, Σ, μ_Δ, Σ_Δ, cov[x, Δ])."""

    def moment_terms(self, *joint: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        self.joint = tuple(t.detach() for t in joint)
        return super().moment_terms(*joint)


def speed(gp, policy, reward, kinematics: Kinematics = CARTPOLE, **kwargs) -> MomentMatching:
    """Moment matching with speed integration on the cart-pole-like parts."""
    return MomentMatching(gp, policy, reward, angle_dims=(2,), integration="speed", kinematics=kinematics, **kwargs)


def recording(kinematics: Kinematics = LONG_PERIOD) -> Recording:
    """A :class:`Recording` with the speed integration's A and J."""
    integration = SpeedIntegration(4, kinematics)
    return Recording(integration.advance, integration.scatter, integration.outputs)


def test_the_gp_is_evaluated_on_the_modelled_outputs_only(gp_factory):
    gp, policy, reward = cartpole_parts(gp_factory)
    propagator = speed(gp, policy, reward)
    assert propagator.dynamics.num_out == len(MODELLED) and propagator.dynamics.weights.shape[-3] == 3  # 3 pairs
    torch.testing.assert_close(propagator.noise_variance, gp.posterior_cache().hyperparameters.noise_variance[MODELLED])
    full = MomentMatching(gp, policy, reward, angle_dims=(2,))
    assert full.dynamics.num_out == 4 and full.dynamics.weights.shape[-3] == 10


def test_moment_terms_are_the_linear_map_of_the_joint_gaussian():
    # x_{t+1} = [x_t, Δ] G with G = [A; J]: mean [μ, μ_Δ] G and covariance Gᵀ P G, P the joint's covariance.
    integration = SpeedIntegration(5, Kinematics((0, 3), (4, 1), 0.7))
    gen = torch.Generator().manual_seed(4)
    root = torch.randn(3, 8, 8, generator=gen, dtype=DTYPE)
    joint_cov = root @ root.mT
    joint_mean = torch.randn(3, 8, generator=gen, dtype=DTYPE)
    mean, cov, delta_mean, delta_cov, cross = integration.moment_terms(
        joint_mean[:, :5], joint_cov[:, :5, :5], joint_mean[:, 5:], joint_cov[:, 5:, 5:], joint_cov[:, :5, 5:])
    stacked = torch.cat([integration.advance, integration.scatter], dim=0)  # G `(D + E') x D`
    torch.testing.assert_close(mean + delta_mean, joint_mean @ stacked, rtol=1e-14, atol=1e-14)
    torch.testing.assert_close(cov + delta_cov + cross + cross.mT, stacked.T @ joint_cov @ stacked, rtol=1e-13,
                               atol=1e-13)
    assert torch.equal(cov, cov.mT) and torch.equal(delta_cov, delta_cov.mT)


@pytest.mark.parametrize("engine", ["reference", "fused"])
@pytest.mark.parametrize("include_noise", [False, True])
def test_one_step_equals_a_monte_carlo_of_the_joint_through_the_linear_map(gp_factory, mc, engine, include_noise):
    # (x_t, Δ) drawn from the step's own joint Gaussian (and ε ~ N(0, diag σ_ε²) with include_noise), mapped by
    # x_t A + (Δ + ε) J: mean and covariance within 5 standard errors (200 000 draws). T = 1.5 s so that the
    # positions' share of the velocities' terms is well above the Monte Carlo error.
    gp, policy, reward = cartpole_parts(gp_factory)
    integration = recording()
    propagator = MomentMatching(gp, policy, reward, angle_dims=(2,), integration=integration,
                                include_noise=include_noise, engine=ENGINES[engine])
    with torch.no_grad():
        nxt, _ = propagator.step(start())
    cov = integration.joint[1]
    x, delta = joint_draws(integration.joint, 200_000, torch.Generator().manual_seed(7),
                           propagator.noise_variance if include_noise else None)
    full = torch.zeros_like(x)
    full[:, MODELLED] = delta
    stepped = trapezoid(x, full, LONG_PERIOD)  # written out, not the integration's A and J
    centred = stepped - stepped.mean(0)
    assert nxt.cov[0, 0] > 2 * cov[0, 0]  # the positions do take their velocities' spread
    mc.assert_mean(nxt.mean, stepped, "next mean")
    mc.assert_mean(nxt.cov, centred[:, :, None] * centred[:, None, :], "next covariance")


def test_speed_follows_a_monte_carlo_of_the_gp_and_the_trapezoid_rule_where_delta_does_not(gp_factory, posterior):
    # A Monte Carlo of the actual step: x_t drawn, u = π(φ(x_t)), the GP's latent Δ of the velocities drawn from its
    # predictive at [φ(x_t), u], positions by the trapezoid rule. Moment matching's Gaussian input is an
    # approximation (φ and π are not linear), so the tolerance is the approximation's, 2e-3 on a narrow start; the
    # delta step's positions follow the GP's Δq instead and miss by far more. Velocities: the same in both steps.
    gp, policy, reward = cartpole_parts(gp_factory)
    narrow = Gaussian(start().mean, 0.05 * start().cov)
    kinematics = LONG_PERIOD
    with torch.no_grad():
        by_speed, _ = speed(gp, policy, reward, kinematics).step(narrow)
        by_delta, _ = MomentMatching(gp, policy, reward, angle_dims=(2,)).step(narrow)
        gen = torch.Generator().manual_seed(11)
        x = narrow.mean + torch.randn(200_000, 4, generator=gen, dtype=DTYPE) @ torch.linalg.cholesky(narrow.cov).T
        features = AngleFeatures(4, (2,))(x)
        mean, var = posterior(gp.posterior_cache(), torch.cat([features, policy(features)], dim=-1))
        draw = mean + var.clamp_min(0.0).sqrt() * torch.randn(mean.shape, generator=gen, dtype=DTYPE)
        full = torch.zeros_like(x)
        full[:, MODELLED] = draw[:, MODELLED]
        stepped = trapezoid(x, full, kinematics)
    positions = list(kinematics.positions)
    torch.testing.assert_close(by_speed.mean, stepped.mean(0), rtol=0, atol=2e-3)
    torch.testing.assert_close(by_speed.cov, stepped.T.cov(), rtol=0, atol=2e-3)
    assert (by_delta.mean[positions] - stepped.mean(0)[positions]).abs().max() > 0.05
    torch.testing.assert_close(by_speed.mean[MODELLED], by_delta.mean[MODELLED], rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(by_speed.cov[MODELLED][:, MODELLED], by_delta.cov[MODELLED][:, MODELLED], rtol=1e-12,
                               atol=1e-14)


@pytest.mark.parametrize("engine", ["reference", "fused", "native"])
@pytest.mark.parametrize("include_noise", [False, True])
def test_an_identity_map_with_every_output_modelled_is_todays_step_bit_for_bit(gp_factory, engine, include_noise):
    # T = 0, no positions: A = I, J = I over all D outputs. Rollout and states equal the delta step's exactly, and so
    # does ∂V/∂ψ under reference. The fused step symmetrizes Aᵀ Σ A and Jᵀ Σ_Δ J, whose backward spreads the gradient
    # of an (exactly symmetric) covariance evenly over its two triangles: the same ∂V/∂ψ, to round-off.
    gp, policy, reward = cartpole_parts(gp_factory)
    eye = torch.eye(4, dtype=DTYPE)
    identity = LinearIntegration(eye, eye.clone(), range(4))

    def run(integration: str | LinearIntegration) -> tuple[Gaussian, Tensor, tuple[Tensor, ...]]:
        propagator = MomentMatching(gp, policy, reward, angle_dims=(2,), integration=integration,
                                    include_noise=include_noise, engine=ENGINES[engine])
        rollout = propagator.rollout(start(), 4)
        return rollout.states, rollout.value, torch.autograd.grad(rollout.value, list(policy.parameters()))

    (states, value, grads), (expected_states, expected_value, expected_grads) = run(identity), run("delta")
    assert torch.equal(value, expected_value)
    assert torch.equal(states.mean, expected_states.mean) and torch.equal(states.cov, expected_states.cov)
    for got, expected in zip(grads, expected_grads, strict=True):
        if engine == "reference":
            assert torch.equal(got, expected)
        torch.testing.assert_close(got, expected, rtol=0, atol=1e-13 * float(expected.abs().max()))


@pytest.mark.parametrize("include_noise", [False, True])
def test_the_engines_agree(gp_factory, include_noise):
    # reference, fused (torch) and native (compiled) moments: V and ∂V/∂ψ of a speed-integrated rollout to 1e-10.
    gp, policy, reward = cartpole_parts(gp_factory)
    psi = list(policy.parameters())
    results = {}
    for name, engine in ENGINES.items():
        value = speed(gp, policy, reward, LONG_PERIOD, include_noise=include_noise, engine=engine).expected_return(
            start(), 5)
        results[name] = (value, torch.autograd.grad(value, psi))
    value, grads = results["reference"]
    for name in ("fused", "native"):
        torch.testing.assert_close(results[name][0], value, rtol=ENGINE_RTOL, atol=0, msg=name)
        for got, expected in zip(results[name][1], grads, strict=True):
            torch.testing.assert_close(got, expected, rtol=ENGINE_RTOL, atol=1e-14, msg=name)


def test_fused_speed_step_keeps_the_covariance_exactly_symmetric(gp_factory):
    gp, policy, reward = cartpole_parts(gp_factory)
    propagator = speed(gp, policy, reward, LONG_PERIOD, include_noise=True, engine=ENGINES["fused"])
    with torch.no_grad():
        states = propagator.rollout(start(), 5).states
    assert torch.equal(states.cov, states.cov.mT)


@pytest.mark.parametrize("engine", ["reference", "fused", "native"])
def test_gradcheck_speed_integrated_rollout(gp_factory, engine):
    gp, policy, reward = cartpole_parts(gp_factory, num_basis=3)
    propagator = speed(gp, policy, reward, LONG_PERIOD, engine=ENGINES[engine])
    near = Gaussian(start().mean, 0.05 * start().cov)
    assert gradcheck_value_wrt_policy_and_start(policy, lambda s: propagator.rollout(s, 2).value, near)


def test_gradcheck_step_wrt_state_mean_and_covariance(gp_factory):
    gp, policy, reward = cartpole_parts(gp_factory, num_basis=3)
    propagator = speed(gp, policy, reward, LONG_PERIOD, include_noise=True)

    def step(mean: Tensor, root: Tensor) -> tuple[Tensor, Tensor]:
        nxt, _ = propagator.step(Gaussian(mean, root @ root.mT + 1e-3 * torch.eye(4, dtype=DTYPE)))
        return nxt.mean, nxt.cov

    root = (0.2 * torch.linalg.cholesky(start().cov)).requires_grad_()
    assert torch.autograd.gradcheck(step, (start().mean.clone().requires_grad_(), root))


def test_stacked_models_and_restarts_match_each_alone(gp_factory):
    # `M` stacked caches: each model's value is that of the model alone.
    gps = [cartpole_parts(gp_factory)[0], gp_factory(40, 4, 1, (2,), seed=77)]
    _, policy, reward = cartpole_parts(gp_factory)
    stacked = speed([g.posterior_cache() for g in gps], policy, reward).expected_return(start(), 3)
    alone = torch.stack([speed(g, policy, reward).expected_return(start(), 3) for g in gps])
    torch.testing.assert_close(stacked, alone, rtol=1e-12, atol=0)


def test_speed_needs_kinematics_and_a_known_name(gp_factory):
    gp, policy, reward = cartpole_parts(gp_factory)
    with pytest.raises(UserError, match="needs the task's kinematics"):
        MomentMatching(gp, policy, reward, angle_dims=(2,), integration="speed")
    with pytest.raises(UserError, match=r"propagation\.integration must be one of delta, speed"):
        MomentMatching(gp, policy, reward, angle_dims=(2,), integration="euler", kinematics=CARTPOLE)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [(("task=pendulum", "propagation.integration=speed"), "task pendulum declares no kinematics"),
     (("propagation.integration=euler",), "propagation.integration must be one of delta, speed"),
     (("propagation.integration=speed", "task.kinematics.velocities=[1]"), "as many velocities as positions")],
)
def test_build_refuses_speed_moment_matching_it_cannot_do_before_any_work(overrides, message):
    with pytest.raises(UserError, match=message):
        build(tiny_config("propagation=moment_matching", *overrides))


def test_build_binds_the_tasks_kinematics_to_moment_matching(gp_factory):
    parts = build(tiny_config("propagation=moment_matching", "propagation.integration=speed"))
    gp, policy, reward = cartpole_parts(gp_factory)
    propagator = parts.make_propagator(gp, policy, reward, angle_dims=(2,))
    assert isinstance(propagator, MomentMatching)
    assert propagator.integration.outputs == (1, 3) and propagator.integration.period == 0.1
    delta = build(tiny_config("propagation=moment_matching")).make_propagator(gp, policy, reward, angle_dims=(2,))
    assert delta.dynamics.num_out == 4
