"""Outputs of a constant Δ, deterministic in both propagators: x_{t+1} = x_t A + Δ J + b, exact, with its gradients."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor

from qtl.features import AngleFeatures
from qtl.gaussian import Gaussian
from qtl.kernels.engine import Engine
from qtl.models import DynamicsGP
from qtl.propagation import MomentMatching, Particles
from qtl.propagation.integration import LinearIntegration, OffsetIntegration, SpeedIntegration
from tests.helpers import gradcheck_value_wrt_policy_and_start, squashed_rbf_parts
from tests.propagation.reference import assert_marginal_paths, joint_draws
from tests.propagation.test_integration import CARTPOLE, LONG_PERIOD, cartpole_parts, trapezoid

DTYPE = torch.float64
# A 3-D state whose dimension 2 (say a contact force) moves by the same C each step; 0 and 1 are learned.
CONSTANT, C = 2, 0.3
LEARNED = [0, 1]


def parts(gp_factory, num_basis: int = 5) -> tuple:
    """A GP of all three outputs (the reference), its deterministic twin, a squashed RBF policy and a reward."""
    gp, policy, reward = squashed_rbf_parts(gp_factory, 3, (), num_basis, seeds=(51, 52))
    twin = DynamicsGP(gp.train_x, gp.train_y[:, LEARNED], gp.hyperparameters.select(torch.tensor(LEARNED)),
                      outputs=LEARNED, state_dim=3, constant_outputs=(CONSTANT,),
                      constant_delta=torch.tensor([C], dtype=DTYPE))
    return gp, twin, policy, reward


def start(scale: float = 1.0) -> Gaussian:
    """A start distribution of the 3-D state."""
    return Gaussian(torch.tensor([0.2, -0.4, 1.0], dtype=DTYPE),
                    scale * torch.diag(torch.tensor([0.05, 0.08, 0.03], dtype=DTYPE)))


def with_constant(x: Tensor, delta: Tensor) -> Tensor:
    """The step written out: x + Δ on the learned outputs, x + C on the constant one (``delta`` `... x 3`)."""
    out = x + delta
    out[..., CONSTANT] = x[..., CONSTANT] + C
    return out


class Recording(OffsetIntegration):
    """An offset step that keeps what the moment-matching step hands it: (μ, Σ, μ_Δ, Σ_Δ, cov[x, Δ])."""

    def moment_terms(self, *joint: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        self.joint = tuple(t.detach() for t in joint)
        return super().moment_terms(*joint)


def test_the_delta_step_of_a_model_with_a_constant_output_is_the_offset_map(gp_factory):
    _, twin, policy, reward = parts(gp_factory)
    propagator = MomentMatching(twin, policy, reward)
    integration = propagator.integration
    assert isinstance(integration, OffsetIntegration) and integration.outputs == (0, 1)
    torch.testing.assert_close(integration.advance, torch.eye(3, dtype=DTYPE), rtol=0, atol=0)
    torch.testing.assert_close(integration.scatter, torch.eye(3, dtype=DTYPE)[LEARNED], rtol=0, atol=0)
    torch.testing.assert_close(integration.offset, torch.tensor([0.0, 0.0, C], dtype=DTYPE), rtol=0, atol=0)
    assert propagator.dynamics.num_out == 2  # no GP of the constant output


@pytest.mark.parametrize("engine", ["reference", "fused"])
@pytest.mark.parametrize("include_noise", [False, True])
def test_one_step_equals_a_monte_carlo_of_the_joint_through_the_offset_map(gp_factory, mc, engine, include_noise):
    # (x_t, Δ) from the step's own joint Gaussian, ε ~ N(0, diag σ_ε²) of the learned outputs with include_noise,
    # mapped by x_t + (Δ + ε) J + b: mean and covariance within 5 standard errors (200 000 draws).
    _, twin, policy, reward = parts(gp_factory)
    eye = torch.eye(3, dtype=DTYPE)
    integration = Recording(eye, eye[LEARNED], LEARNED, torch.tensor([0.0, 0.0, C], dtype=DTYPE))
    propagator = MomentMatching(twin, policy, reward, integration=integration, include_noise=include_noise,
                                engine=Engine(moments=engine))
    with torch.no_grad():
        nxt, _ = propagator.step(start())
    x, delta = joint_draws(integration.joint, 200_000, torch.Generator().manual_seed(8),
                           propagator.noise_variance if include_noise else None)
    stepped = with_constant(x, torch.cat([delta, torch.zeros(200_000, 1, dtype=DTYPE)], dim=-1))
    centred = stepped - stepped.mean(0)
    mc.assert_mean(nxt.mean, stepped, "next mean")
    mc.assert_mean(nxt.cov, centred[:, :, None] * centred[:, None, :], "next covariance")
    # Deterministic: the constant dimension moves by C exactly, and takes no variance or covariance from Δ.
    torch.testing.assert_close(nxt.mean[CONSTANT], start().mean[CONSTANT] + C, rtol=1e-15, atol=0)
    torch.testing.assert_close(nxt.cov[CONSTANT, CONSTANT], start().cov[CONSTANT, CONSTANT], rtol=1e-14, atol=0)


def test_moment_matching_follows_a_monte_carlo_of_the_gp_and_the_constant_step(gp_factory, posterior):
    # The whole step sampled: x_t drawn, u = π(x_t), the GP's latent Δ of the learned outputs drawn from its
    # predictive, the constant output + C. Moment matching's Gaussian input is an approximation (π is not linear):
    # the tolerance is the approximation's, 2e-3 on a narrow start.
    gp, twin, policy, reward = parts(gp_factory)
    narrow = start(0.05)
    with torch.no_grad():
        nxt, _ = MomentMatching(twin, policy, reward).step(narrow)
        gen = torch.Generator().manual_seed(12)
        x = narrow.mean + torch.randn(200_000, 3, generator=gen, dtype=DTYPE) @ torch.linalg.cholesky(narrow.cov).T
        mean, var = posterior(gp.posterior_cache(), torch.cat([x, policy(x)], dim=-1))
        stepped = with_constant(x, mean + var.clamp_min(0.0).sqrt() * torch.randn(mean.shape, generator=gen,
                                                                                    dtype=DTYPE))
    torch.testing.assert_close(nxt.mean, stepped.mean(0), rtol=0, atol=2e-3)
    torch.testing.assert_close(nxt.cov, stepped.T.cov(), rtol=0, atol=2e-3)


@pytest.mark.parametrize("include_noise", [False, True])
def test_marginal_particles_step_the_constant_output_by_its_delta(gp_factory, posterior, include_noise):
    # Per particle: the learned outputs drawn from the GP's predictive with the propagator's noise columns, the
    # constant output + C exactly.
    gp, twin, policy, reward = parts(gp_factory)
    particles = Particles(twin, policy, reward, num_particles=16, seed=4, include_noise=include_noise)
    assert_marginal_paths(particles, gp, policy, start(), 4, posterior, include_noise, with_constant)


def test_pathwise_particles_step_the_constant_output_by_its_delta(gp_factory):
    # Functions are drawn for the two learned outputs only; the constant output moves by C exactly.
    _, twin, policy, reward = parts(gp_factory)
    settings = {"num_particles": 16, "seed": 4, "sampling": "pathwise", "num_features": 32}
    with torch.no_grad():
        states, _ = Particles(twin, policy, reward, **settings).trajectories(start(), 4)
        functions = Particles(twin, policy, reward, **settings).functions()
    assert functions.update.shape[-3] == 2
    steps = torch.arange(5, dtype=DTYPE)
    torch.testing.assert_close(states[:, :, CONSTANT] - states[:, :1, CONSTANT], C * steps.expand(16, 5),
                               rtol=0, atol=1e-14)


def test_expected_reward_scores_the_gaussian_of_the_drawn_step_with_no_variance_on_the_constant(gp_factory):
    _, twin, policy, reward = parts(gp_factory)
    particles = Particles(twin, policy, reward, num_particles=8, seed=2, expected_reward=True)
    with torch.no_grad():
        states, _, predictive = particles._paths(start(), 2, None)
    assert torch.equal(predictive.cov[..., CONSTANT, :], torch.zeros_like(predictive.cov[..., CONSTANT, :]))
    torch.testing.assert_close(predictive.mean[..., CONSTANT], states[:, 1:, CONSTANT], rtol=0, atol=1e-14)


def test_speed_integration_of_a_constant_velocity_puts_its_delta_in_the_offset(gp_factory):
    # Cart-pole layout (x, ẋ, θ, θ̇): θ̇'s Δ constant, so θ = θ + T θ̇ + (T/2) C and θ̇ = θ̇ + C; ẋ learned.
    gp, policy, reward = cartpole_parts(gp_factory)
    twin = DynamicsGP(gp.train_x, gp.train_y[:, [1]], gp.hyperparameters.select(torch.tensor([1])), outputs=(1,),
                      state_dim=4, constant_outputs=(3,), constant_delta=torch.tensor([C], dtype=DTYPE))
    particles = Particles(twin, policy, reward, angle_dims=(2,), num_particles=8, seed=3, integration="speed",
                          kinematics=CARTPOLE)
    integration = particles.integration
    assert isinstance(integration, OffsetIntegration) and integration.outputs == (1,)
    gen = torch.Generator().manual_seed(2)
    x, drawn = torch.randn(5, 4, generator=gen, dtype=DTYPE), torch.randn(5, 1, generator=gen, dtype=DTYPE)
    full = torch.zeros(5, 4, dtype=DTYPE)
    full[:, 1], full[:, 3] = drawn[:, 0], C
    torch.testing.assert_close(integration.step(x, drawn), trapezoid(x, full), rtol=1e-14, atol=1e-14)
    plain = SpeedIntegration(4, CARTPOLE)
    assert isinstance(plain, LinearIntegration) and plain.outputs == (1, 3)


def test_a_model_missing_an_output_of_the_step_is_refused(gp_factory):
    gp, policy, reward = cartpole_parts(gp_factory)
    twin = DynamicsGP(gp.train_x, gp.train_y[:, [0]], gp.hyperparameters.select(torch.tensor([0])), outputs=(0,),
                      state_dim=4, constant_outputs=(3,), constant_delta=torch.tensor([C], dtype=DTYPE))
    with pytest.raises(ValueError, match=r"missing"):
        MomentMatching(twin, policy, reward, angle_dims=(2,), integration="speed", kinematics=LONG_PERIOD)


@pytest.mark.parametrize("engine", ["reference", "fused"])
def test_gradcheck_moment_matching_with_a_constant_output(gp_factory, engine):
    _, twin, policy, reward = parts(gp_factory, num_basis=3)
    propagator = MomentMatching(twin, policy, reward, engine=Engine(moments=engine))
    assert gradcheck_value_wrt_policy_and_start(policy, lambda s: propagator.rollout(s, 2).value, start(0.3))


@pytest.mark.parametrize(("sampling", "expected_reward"), [("marginal", False), ("marginal", True),
                                                           ("pathwise", False)])
def test_gradcheck_particles_with_a_constant_output(gp_factory, sampling, expected_reward):
    _, twin, policy, reward = parts(gp_factory, num_basis=3)
    particles = Particles(twin, policy, reward, num_particles=6, sampling=sampling, num_features=16,
                          expected_reward=expected_reward, seed=2)
    assert gradcheck_value_wrt_policy_and_start(policy, lambda s: particles.rollout(s, 2).value, start(0.3))


def test_features_of_the_state_are_unchanged_by_the_constant_output(gp_factory):
    _, twin, policy, reward = parts(gp_factory)
    assert MomentMatching(twin, policy, reward).features.state_dim == AngleFeatures(3, ()).state_dim == 3
