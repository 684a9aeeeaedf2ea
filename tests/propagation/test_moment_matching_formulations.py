"""MomentMatching under the fused formulation against the reference one: rollout values and ∂V/∂ψ."""

from __future__ import annotations

import logging

import pytest
import torch

from qtl.build import build
from qtl.errors import UserError
from qtl.gaussian import Gaussian
from qtl.kernels import engine as engine_module
from qtl.kernels.engine import Engine
from qtl.kernels.native import build as native_build
from qtl.kernels.native import loader
from qtl.policies import LinearPolicy, Policy, RBFPolicy, SquashedPolicy
from qtl.propagation import MomentMatching
from tests.helpers import gradcheck_value_wrt_policy_and_start, quadratic_reward, tiny_config
from tests.propagation.restarts import random_start, spread_restarts
from tests.test_features import assert_rel_close

DTYPE = torch.float64
HORIZON = 6


def make_policy(kind: str, input_dim: int) -> Policy:
    gen = torch.Generator().manual_seed(3)
    if kind == "linear":
        return SquashedPolicy(LinearPolicy(input_dim, 1, generator=gen), 2.0)
    targets = torch.randn(6, 1, generator=gen, dtype=DTYPE)
    return SquashedPolicy(RBFPolicy(input_dim, 1, 6, targets=targets, generator=gen), 2.0)


@pytest.mark.parametrize(
    ("kind", "restarts", "models", "include_noise"),
    [("rbf", 1, 1, False), ("rbf", 3, 1, False), ("rbf", 1, 2, False), ("rbf", 1, 1, True), ("linear", 3, 1, False)],
)
def test_rollout_formulations_agree(gp_factory, kind, restarts, models, include_noise):
    """V and ∂V/∂ψ (restarts `R` as ψ's batch, stacked models `M`) of the two formulations agree to 1e-12."""
    gps = [gp_factory(30, 3, 1, (1,), seed=51 + m) for m in range(models)]
    model = [g.posterior_cache() for g in gps] if models > 1 else gps[0]
    policy = make_policy(kind, 4)
    if restarts > 1:
        policy = spread_restarts(policy, restarts)
    def propagator(moments: str) -> MomentMatching:
        return MomentMatching(model, policy, quadratic_reward(3, (1,)), angle_dims=(1,), include_noise=include_noise,
                              engine=Engine(moments=moments))

    gen = torch.Generator().manual_seed(restarts + models)
    start = random_start(models, gen)
    psi = list(policy.parameters())

    fused = propagator("fused").expected_return(start, HORIZON)
    reference = propagator("reference").expected_return(start, HORIZON)
    assert fused.shape == reference.shape == ((restarts,) if restarts > 1 else (models,) if models > 1 else ())
    assert_rel_close(fused, reference, "V")
    weights = torch.randn(fused.shape, generator=gen, dtype=DTYPE)
    grads_fused = torch.autograd.grad((fused * weights).sum(), psi)
    grads_reference = torch.autograd.grad((reference * weights).sum(), psi)
    for p, g, w in zip(psi, grads_fused, grads_reference, strict=True):
        assert g.shape == p.shape
        assert_rel_close(g, w, "∂V/∂ψ")


def test_fused_step_keeps_the_covariance_exactly_symmetric(gp_factory):
    gp = gp_factory(30, 3, 1, (1,), seed=61)
    propagator = MomentMatching(gp, make_policy("rbf", 4), quadratic_reward(3, (1,)), angle_dims=(1,),
                                engine=Engine(moments="fused"))
    gen = torch.Generator().manual_seed(0)
    root = 0.4 * torch.randn(3, 3, generator=gen, dtype=DTYPE)
    with torch.no_grad():
        states = propagator.rollout(Gaussian(torch.zeros(3, dtype=DTYPE), root @ root.T), HORIZON).states
    assert torch.equal(states.cov, states.cov.mT)


def test_gradcheck_fused_three_step_rollout(gp_factory):
    gp = gp_factory(10, 2, 1, (1,), seed=41)
    policy = SquashedPolicy(RBFPolicy(3, 1, 3, generator=torch.Generator().manual_seed(2)), 1.0)
    propagator = MomentMatching(gp, policy, quadratic_reward(2, (1,)), angle_dims=(1,), engine=Engine(moments="fused"))
    start = Gaussian(torch.tensor([0.1, 0.4], dtype=DTYPE), 0.05 * torch.eye(2, dtype=DTYPE))
    assert gradcheck_value_wrt_policy_and_start(policy, lambda s: propagator.expected_return(s, 3), start)


def test_kernels_moments_is_chosen_in_build_and_a_bad_one_is_refused():
    assert build(tiny_config("kernels.moments=fused")).engine.moments == "fused"
    native_build.build()
    parts = build(tiny_config())
    assert parts.engine.moments == "native"  # the default, auto: native where the build loads
    assert parts.make_propagator.keywords["engine"] is parts.engine  # every propagator gets it
    assert build(tiny_config("kernels.moments=reference")).engine.moments == "reference"
    with pytest.raises(UserError, match=r"kernels\.moments must be one of"):
        build(tiny_config("kernels.moments=fast"))


def test_native_and_auto_need_the_build_and_auto_falls_back_to_fused(monkeypatch, caplog, tmp_path):
    """moments=native refuses a missing build in one line; auto takes native when built, else fused (logged once)."""
    native_build.build()
    assert Engine.resolve("torch", "auto").moments == "native"
    monkeypatch.setattr(loader, "library_path", lambda: tmp_path / "missing.so")
    with pytest.raises(UserError, match=r"kernels\.moments=native, but .* build them with"):
        Engine.resolve("torch", "native")
    engine_module._log_once.cache_clear()
    with caplog.at_level(logging.INFO, logger=engine_module.__name__):
        assert Engine.resolve("torch", "auto").moments == "fused"
        assert Engine.resolve("torch", "auto").moments == "fused"
    assert sum("using kernels.moments=fused" in r.getMessage() for r in caplog.records) == 1
