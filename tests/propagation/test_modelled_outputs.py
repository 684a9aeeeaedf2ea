"""A GP fitted on the modelled outputs only (speed integration) propagates as the GP of every output cut to them."""

from __future__ import annotations

import itertools

import pytest
import torch

from qtl.kernels.engine import Engine
from qtl.models import DynamicsGP, SparseDynamicsGP
from qtl.propagation import MomentMatching, Particles
from qtl.propagation.gp_cache import cache_tensors
from qtl.propagation.integration import SpeedIntegration, modelled_outputs, select_outputs
from tests.propagation.test_integration import CARTPOLE, LONG_PERIOD, MODELLED, cartpole_parts, start

DTYPE = torch.float64
# The outputs are independent GPs, so the cut is exact; the batched solves of E' and of D outputs may round
# differently (the batch size picks the kernel), hence round-off and not bit-for-bit.
CUT_RTOL, CUT_ATOL = 1e-11, 1e-13


def modelled_twin(gp: DynamicsGP) -> DynamicsGP:
    """``gp``'s data and θ of the velocities only: the model the loop now fits under speed integration."""
    return DynamicsGP(gp.train_x, gp.train_y[:, MODELLED], gp.hyperparameters.select(torch.tensor(MODELLED)),
                      outputs=MODELLED, state_dim=4)


def test_a_model_of_the_modelled_outputs_names_them_in_its_cache(gp_factory):
    gp, _, _ = cartpole_parts(gp_factory)
    twin = modelled_twin(gp)
    assert twin.num_outputs == 2 and twin.outputs == (1, 3) and twin.state_dim == 4
    assert twin.posterior_cache().outputs == (1, 3) and twin.posterior_cache().state_dim == 4
    assert gp.outputs == (0, 1, 2, 3) and gp.state_dim == 4  # a model that names none models all
    assert modelled_outputs("speed", 4, CARTPOLE) == (1, 3) and modelled_outputs("delta", 4, CARTPOLE) == (0, 1, 2, 3)


def test_the_cache_of_the_modelled_outputs_is_the_full_cache_cut(gp_factory):
    gp, _, _ = cartpole_parts(gp_factory)
    full, twin = cache_tensors(gp), cache_tensors(modelled_twin(gp))
    cut = select_outputs(full, MODELLED)
    assert cut.keys() == twin.keys()
    for name in cut:
        torch.testing.assert_close(twin[name], cut[name], rtol=CUT_RTOL, atol=CUT_ATOL, msg=name)


@pytest.mark.parametrize(("engine", "include_noise"), list(itertools.product(["reference", "fused"], [False, True])))
def test_moment_matching_through_the_modelled_model_equals_todays_cut(gp_factory, engine, include_noise):
    gp, policy, reward = cartpole_parts(gp_factory)
    settings = {"angle_dims": (2,), "integration": "speed", "kinematics": LONG_PERIOD, "include_noise": include_noise,
                "engine": Engine(moments=engine)}
    today = MomentMatching(gp, policy, reward, **settings)
    modelled = MomentMatching(modelled_twin(gp), policy, reward, **settings)
    assert modelled.dynamics.num_out == 2 and modelled.integration.outputs == (1, 3)
    expected, got = today.rollout(start(), 4), modelled.rollout(start(), 4)
    torch.testing.assert_close(got.value, expected.value, rtol=CUT_RTOL, atol=0)
    torch.testing.assert_close(got.states.cov, expected.states.cov, rtol=CUT_RTOL, atol=CUT_ATOL)
    grads = [torch.autograd.grad(r.value, list(policy.parameters())) for r in (expected, got)]
    for want, have in zip(*grads, strict=True):
        torch.testing.assert_close(have, want, rtol=1e-9, atol=1e-13)


@pytest.mark.parametrize(("sampling", "expected_reward"),
                         [("marginal", False), ("marginal", True), ("pathwise", False)])
def test_particles_through_the_modelled_model_equal_todays_cut(gp_factory, sampling, expected_reward):
    gp, policy, reward = cartpole_parts(gp_factory)
    settings = {"angle_dims": (2,), "integration": "speed", "kinematics": CARTPOLE, "num_particles": 16, "seed": 3,
                "sampling": sampling, "num_features": 32, "expected_reward": expected_reward}
    today = Particles(gp, policy, reward, **settings)
    modelled = Particles(modelled_twin(gp), policy, reward, **settings)
    with torch.no_grad():
        expected, got = today.trajectories(start(), 4)[0], modelled.trajectories(start(), 4)[0]
    torch.testing.assert_close(got, expected, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(modelled.rollout(start(), 4).value, today.rollout(start(), 4).value, rtol=1e-10, atol=0)


def test_a_sparse_model_of_the_modelled_outputs_is_the_full_sparse_model_cut(gp_factory):
    gp, policy, reward = cartpole_parts(gp_factory)
    z = gp.train_x[::3].clone()
    full = SparseDynamicsGP(gp.train_x, gp.train_y, gp.hyperparameters, inducing_points=z)
    twin = SparseDynamicsGP(gp.train_x, gp.train_y[:, MODELLED], gp.hyperparameters.select(torch.tensor(MODELLED)),
                            inducing_points=z, outputs=MODELLED, state_dim=4)
    cut = select_outputs(cache_tensors(full), MODELLED)
    for name, value in cache_tensors(twin).items():
        torch.testing.assert_close(value, cut[name], rtol=1e-9, atol=1e-11, msg=name)
    assert twin.exact().outputs == (1, 3)
    settings = {"angle_dims": (2,), "integration": "speed", "kinematics": CARTPOLE}
    torch.testing.assert_close(MomentMatching(twin, policy, reward, **settings).expected_return(start(), 3),
                               MomentMatching(full, policy, reward, **settings).expected_return(start(), 3),
                               rtol=1e-9, atol=0)


def test_a_model_of_other_outputs_than_the_step_is_refused(gp_factory):
    gp, policy, reward = cartpole_parts(gp_factory)
    other = DynamicsGP(gp.train_x, gp.train_y[:, [0, 1]], gp.hyperparameters.select(torch.tensor([0, 1])),
                       outputs=(0, 1), state_dim=4)
    with pytest.raises(ValueError, match=r"the step models outputs \[1, 3\], the GP outputs \[0, 1\]"):
        MomentMatching(other, policy, reward, angle_dims=(2,), integration="speed", kinematics=CARTPOLE)
    with pytest.raises(ValueError, match=r"integration delta steps every state dimension.*\[1, 3\] of 4"):
        Particles(modelled_twin(gp), policy, reward, angle_dims=(2,), num_particles=4)


def test_stacked_caches_must_name_the_same_outputs(gp_factory):
    gp, _, _ = cartpole_parts(gp_factory)
    with pytest.raises(ValueError, match="must share n, D, E, outputs"):
        cache_tensors([modelled_twin(gp).posterior_cache(),
                       DynamicsGP(gp.train_x, gp.train_y[:, [0, 2]], gp.hyperparameters.select(torch.tensor([0, 2])),
                                  outputs=(0, 2), state_dim=4).posterior_cache()])


def test_the_speed_step_takes_a_model_of_its_outputs_as_it_is():
    integration = SpeedIntegration(4, CARTPOLE)
    data = {"outputs": torch.tensor([1, 3]), "beta": torch.zeros(2, 5, dtype=DTYPE)}
    same, kept = integration.for_model(data)
    assert same is integration and kept is data
