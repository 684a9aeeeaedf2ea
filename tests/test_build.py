"""``build(cfg)``: every part of Algorithm 1 made from the config and checked, for the loop and the scripts."""

from __future__ import annotations

import csv
import functools
import logging
import math

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from qtl.build import DTYPES, Parts, build, resolve_device, transfer_plan
from qtl.checkpoint import latest_checkpoint, load_checkpoint
from qtl.config import typed_groups
from qtl.data import TransitionDataset, gp_training_pairs
from qtl.episodes import random_actor, run_episode
from qtl.errors import UserError
from qtl.loop import run
from qtl.models import AutoFit, DynamicsGP, ExactFit, SparseDynamicsGP, SparseFit
from qtl.plateau import PlateauRule
from qtl.policies import RBFNetwork, SquashedPolicy
from qtl.policy_search import AdamSearch, LBFGSSearch
from qtl.propagation import MomentMatching, Particles
from qtl.rewards import AngleDistanceReward
from tests.helpers import TINY, tiny_config, train_config


def test_parts_of_the_default_config():
    parts = build(tiny_config())
    assert parts.dtype == torch.float64 and parts.device == torch.device("cpu")
    assert parts.task.state_dim == 4 and parts.task.horizon == 8
    assert parts.features.output_dim == parts.task.feature_dim
    assert parts.start.mean.dtype == torch.float64 and parts.start.mean.shape == (4,)
    # The TINY budget; sparse_above, inducing: the fitter's defaults; warm starts: the config's default.
    assert parts.model == AutoFit(restarts=1, max_iter=5, warm_start=True)
    assert isinstance(parts.search, LBFGSSearch) and parts.search.restarts == 2
    policy = parts.initial_policy()
    assert isinstance(policy, SquashedPolicy)
    assert isinstance(parts.make_propagator(parts.fit_dynamics(_data(parts), torch.Generator()), policy, parts.reward,
                                            angle_dims=parts.task.angle_dims), MomentMatching)


def test_the_model_group_defaults_to_auto_with_the_fitters_own_defaults_and_warm_starts():
    assert instantiate(tiny_config("model.restarts=3", "model.max_iter=100").model) == AutoFit(warm_start=True)


@pytest.mark.parametrize(("option", "kind"), [("auto", AutoFit), ("exact", ExactFit), ("sparse", SparseFit)])
def test_each_model_option_makes_its_fitter(option, kind):
    assert type(build(tiny_config(f"model={option}")).model) is kind


def test_other_group_options_and_dtype():
    tiny = [o for o in TINY if not o.startswith("optimizer.")]  # L-BFGS's budget: Adam has steps instead
    parts = build(train_config(*tiny, "propagation=particles", "propagation.num_particles=10", "optimizer=adam",
                               "optimizer.steps=2", "dtype=float32"))
    assert parts.dtype == DTYPES["float32"] == torch.float32 and parts.start.mean.dtype == torch.float32
    assert isinstance(parts.search, AdamSearch)
    policy = parts.initial_policy()
    assert all(p.dtype == torch.float32 for p in policy.parameters())
    model = parts.fit_dynamics(_data(parts), torch.Generator().manual_seed(0))
    assert isinstance(parts.make_propagator(model, policy, parts.reward, angle_dims=parts.task.angle_dims), Particles)


def test_initial_policy_is_the_seeds_own():
    a, b = build(tiny_config("seed=2")).initial_policy(), build(tiny_config("seed=2")).initial_policy()
    c = build(tiny_config("seed=3")).initial_policy()
    for name, value in a.state_dict().items():
        torch.testing.assert_close(value, b.state_dict()[name], rtol=0, atol=0)
    assert any(not torch.equal(pa, pc) for pa, pc in zip(a.state_dict().values(), c.state_dict().values(), strict=True))


def test_fit_dynamics_follows_the_model_option():
    parts = build(tiny_config("model.sparse_above=10", "model.inducing=6"))
    data = _data(parts, episodes=2)  # 16 tuples
    model = parts.fit_dynamics(data, torch.Generator().manual_seed(0))
    assert isinstance(model, SparseDynamicsGP) and model.inducing_points.shape[0] == 6
    exact = build(tiny_config("model=exact")).fit_dynamics(data, torch.Generator().manual_seed(0))
    assert type(exact) is DynamicsGP and exact.train_x.shape == (16, parts.task.gp_input_dim)


@pytest.mark.parametrize("option", ["exact", "sparse"])
def test_fit_dynamics_under_speed_integration_fits_the_modelled_outputs_only(option):
    extra = ("model.inducing=6",) if option == "sparse" else ()
    parts = build(tiny_config("propagation.integration=speed", f"model={option}", *extra))
    assert parts.modelled == (1, 3)  # cart-pole: x, ẋ, θ, θ̇; the positions follow their velocities
    model = parts.fit_dynamics(_data(parts, episodes=2), torch.Generator().manual_seed(0))
    assert model.outputs == (1, 3) and model.state_dim == 4 and model.hyperparameters.num_outputs == 2
    _, _, delta = _data(parts, episodes=2).tensors()
    torch.testing.assert_close(model.train_y, delta[:, [1, 3]], rtol=0, atol=0)


def test_fit_dynamics_under_delta_integration_is_the_fit_of_every_output_bit_for_bit():
    parts = build(tiny_config("model=exact"))
    data = _data(parts, episodes=2)
    model = parts.fit_dynamics(data, torch.Generator().manual_seed(0))
    inputs, targets = gp_training_pairs(data, parts.features, parts.dtype)
    plain = ExactFit(restarts=1, max_iter=5).fit(inputs, targets, generator=torch.Generator().manual_seed(0))
    assert model.outputs == (0, 1, 2, 3)
    assert torch.equal(model.hyperparameters.natural(), plain.hyperparameters.natural())


@pytest.mark.parametrize(("override", "message"), [
    ("model.restarts=0", "model.restarts must be >= 1"),
    ("model.inducing=0", "model.inducing must be >= 1"),
    ("optimizer.restarts=0", "restarts must be >= 1"),
])
def test_a_bad_component_setting_fails_in_build_with_its_own_message(override, message):
    with pytest.raises(ValueError, match=message):
        build(tiny_config(override))


def test_transfer_plan_without_a_source_is_pilcos():
    parts = build(tiny_config())
    plan = transfer_plan(tiny_config(), parts)
    assert plan.source is None and not plan.transfer_policy


def test_a_config_stored_before_the_model_group_reads_as_model_auto():
    legacy = OmegaConf.to_container(tiny_config(), resolve=True)
    legacy["model"] = {"restarts": 1, "max_iter": 5, "sparse_above": 10, "inducing": 6}  # no `_target_`
    cfg = typed_groups(OmegaConf.create(legacy))
    assert cfg.model._target_ == "qtl.models.AutoFit"
    assert build(cfg).model == AutoFit(restarts=1, max_iter=5, sparse_above=10, inducing=6,  # warm_start: false
                                       inducing_jitter=0.0)  # (K_mm had no jitter then)


def test_a_config_stored_before_the_inducing_jitter_reads_as_none():
    """A sparse or auto model node stored without `inducing_jitter` ran with K_mm unjittered: it reads 0."""
    for option in ("auto", "sparse"):
        stored = OmegaConf.to_container(tiny_config(f"model={option}"), resolve=True)
        del stored["model"]["inducing_jitter"]
        assert typed_groups(OmegaConf.create(stored)).model.inducing_jitter == 0.0
        assert typed_groups(tiny_config(f"model={option}")).model.inducing_jitter == 1e-6
    assert "inducing_jitter" not in typed_groups(tiny_config("model=exact")).model


def test_a_config_stored_before_the_fast_defaults_reads_with_the_old_values():
    """Keys added before issue 18 flipped their defaults read as their old defaults where a stored config lacks them."""
    legacy = OmegaConf.to_container(tiny_config(), resolve=True)
    del legacy["model"]["warm_start"], legacy["optimizer"]["batched"], legacy["kernels"]
    cfg = typed_groups(OmegaConf.create(legacy))
    assert cfg.model.warm_start is False and cfg.optimizer.batched is False
    assert (cfg.kernels.backend, cfg.kernels.moments) == ("torch", "reference")
    fresh = typed_groups(tiny_config())
    assert fresh.model.warm_start is True and fresh.optimizer.batched is True
    assert (fresh.kernels.backend, fresh.kernels.moments) == ("auto", "auto")


def test_resolve_device_accepts_cpu_and_present_gpus(monkeypatch):
    assert resolve_device("cpu") == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert resolve_device("cuda") == torch.device("cuda")
    assert resolve_device("cuda:1") == torch.device("cuda", 1)


def _data(parts: Parts, episodes: int = 1) -> TransitionDataset:
    """Random-action episodes of the task."""
    data = TransitionDataset(parts.task.state_dim, parts.task.action_dim, parts.task.angle_dims)
    env = parts.task.make_env()
    rng = np.random.default_rng(0)
    for k in range(episodes):
        real = run_episode(env, parts.task, random_actor(parts.task, rng), k)
        data.add_episode(real.states, real.actions)
    env.close()
    return data


def test_kernels_backend_is_chosen_in_build_and_a_bad_one_is_refused():
    from qtl.errors import UserError
    from qtl.kernels.native import load_exp_sum

    try:
        load_exp_sum()
        expected = "native"
    except ImportError:
        expected = "torch"
    torch_parts = build(tiny_config("kernels.backend=torch"))
    assert torch_parts.kernel_backend == "torch" == torch_parts.engine.exp_sums
    parts = build(tiny_config())  # the default: auto
    assert parts.kernel_backend == expected and parts.make_propagator.keywords["engine"] is parts.engine
    with pytest.raises(UserError, match=r"kernels\.backend must be one of"):
        build(tiny_config("kernels.backend=cuda"))


# -- recipe=mc_pilco and policy dropout -----------------------------------------------------------------

# The loop's tiny budget with Adam (L-BFGS's max_iter does not apply).
ADAM_TINY = [o for o in TINY if not o.startswith("optimizer.")]


def test_recipe_mc_pilco_composes_the_particle_recipe():
    cfg = train_config("recipe=mc_pilco")
    prop, policy, opt = cfg.propagation, cfg.policy, cfg.optimizer
    assert prop._target_ == "qtl.propagation.Particles"
    assert (prop.sampling, prop.resample_every, prop.num_features, prop.reward_width_scale) == ("pathwise", 1, 256,
                                                                                                4.0)
    assert prop.path_dtype == "float32"  # the drawn functions evaluated in float32
    assert prop.reward_task_weight == 0.5  # half the search reward is the task's own
    assert policy._target_ == "qtl.policies.rbf_network_policy" and policy.num_basis == 200
    assert opt._target_ == "qtl.policy_search.AdamSearch"
    assert (opt.steps, opt.lr, opt.keep, opt.dropout, opt.dropout_reduction, opt.lr_min, opt.batched, opt.restarts) \
        == (2000, 0.01, "validated", 0.25, 0.125, 0.0025, False, 1)
    assert OmegaConf.to_container(opt.plateau) == {"ema": 0.99, "threshold": 0.08, "window": 200, "min_steps": 200}
    assert cfg.task.env.id == train_config().task.env.id  # the task is untouched
    assert train_config("recipe=mc_pilco", "optimizer.dropout=0.1").optimizer.dropout == 0.1  # overrides win
    assert train_config().optimizer._target_ == "qtl.policy_search.LBFGSSearch"  # recipe: null by default


def test_recipe_mc_pilco_builds_a_dropout_network_searched_by_the_schedule():
    parts = build(train_config(*ADAM_TINY, "recipe=mc_pilco", "policy.num_basis=30"))
    assert isinstance(parts.search, AdamSearch) and parts.search.settings.plateau == PlateauRule(0.99, 0.08, 200, 200)
    policy = parts.initial_policy()
    assert isinstance(policy, SquashedPolicy) and isinstance(policy.policy, RBFNetwork)
    centres = policy.policy.centres.detach()
    assert centres.shape == (30, parts.task.feature_dim)
    angle = centres[:, -2:]  # the cart-pole's (sin θ, cos θ): centres on the unit circle
    torch.testing.assert_close(angle.square().sum(-1), torch.ones(30, dtype=torch.float64))
    policy.set_dropout(0.25)  # the search can switch it on
    assert policy.policy.dropout == 0.25


@pytest.mark.parametrize(("overrides", "fix"), [
    (["optimizer=adam", "policy=rbf_network"], "propagation=particles"),
    (["optimizer=adam", "propagation=particles"], "policy=rbf_network"),
    (["recipe=mc_pilco", "policy=rbf"], "policy=rbf_network"),
])
def test_dropout_without_particles_and_a_network_is_refused_in_one_line(overrides, fix):
    with pytest.raises(UserError, match=r"optimizer\.dropout > 0 needs") as caught:
        build(train_config(*ADAM_TINY, *overrides, "optimizer.dropout=0.25"))
    message = str(caught.value)
    assert "\n" not in message and fix in message and "optimizer.dropout=0" in message


def test_the_mc_pilco_recipe_runs_the_loop_end_to_end(tmp_path, caplog):
    """recipe=mc_pilco shrunk to seconds: one learned episode, its predicted return and evaluations recorded.

    Plateaus (window 3 after 3 steps) can come at steps 5 and 9, not a third within 10 steps: 10 evaluations, then
    keep=validated values the start, a snapshot after each of steps 1-9 (every max(1, 10 // 20) steps) and the end.
    """
    cfg = train_config(*ADAM_TINY, "recipe=mc_pilco", "episodes=1", "optimizer.steps=10", "optimizer.plateau.window=3",
                       "optimizer.plateau.min_steps=3", "propagation.num_particles=20", "policy.num_basis=20",
                       "propagation.num_features=32")
    with caplog.at_level(logging.INFO, logger="qtl.policy_search"):
        result = run(cfg, tmp_path)
    with open(tmp_path / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["kind"] for r in rows] == ["random", "policy"]
    learned = rows[1]
    assert math.isfinite(float(learned["predicted_return"])) and float(learned["predicted_return"]) > 0
    assert int(learned["policy_evaluations"]) == 10 + 1 + 9 + 1
    assert any("plateau after" in r.getMessage() for r in caplog.records)  # the schedule ran
    assert len(result.returns) == 2 and all(math.isfinite(r) for r in result.returns)
    assert (tmp_path / "checkpoints" / "episode_0001.pt").exists()


def test_the_mc_pilco_recipe_transfers_theta_and_psi_unchanged(tmp_path):
    """QTL Bayesian from a recipe source: ψ_s (an RBF network) runs episode 0 of the 2.0 kg target, then θ follows."""
    shrunk = [*ADAM_TINY, "recipe=mc_pilco", "episodes=1", "optimizer.steps=6", "optimizer.plateau=null",
              "propagation.num_particles=20", "policy.num_basis=20", "propagation.num_features=32"]
    source = tmp_path / "source"
    run(train_config(*shrunk), source)
    target = tmp_path / "target"
    run(train_config(*shrunk, "approach=qtl_bayesian", f"transfer.source={source}", "task.env.pole_mass=2.0"), target)
    with open(target / "metrics.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [r["kind"] for r in rows] == ["source_policy", "policy"]
    assert math.isfinite(float(rows[1]["compliance"])) and math.isfinite(float(rows[1]["predicted_return"]))
    psi_s = load_checkpoint(latest_checkpoint(source))["policy"]
    psi_0 = load_checkpoint(target / "checkpoints" / "episode_0000.pt")["policy"]
    assert psi_s.keys() == psi_0.keys() and any("centres" in name for name in psi_s)
    for name, value in psi_s.items():  # episode 0 ran ψ_s and changed nothing
        assert torch.equal(psi_0[name], value), name


def factory_keywords(factory: object) -> dict:
    """The keywords bound on a propagator factory, through its layers of ``functools.partial`` (outer ones win)."""
    keywords: dict = {}
    while isinstance(factory, functools.partial):
        keywords = {**factory.keywords, **keywords}
        factory = factory.func
    return keywords


def test_the_recipe_binds_the_tasks_angle_position_cost_where_it_declares_one():
    """recipe=mc_pilco (search_cost auto): cart-pole's MC-PILCO cost; mountain car (none declared): widened."""
    parts = build(train_config("recipe=mc_pilco"))
    keywords = factory_keywords(parts.make_propagator)
    assert keywords["search_cost"] == "task" and isinstance(keywords["task_search_cost"], AngleDistanceReward)
    cost = keywords["task_search_cost"]
    upright = torch.tensor([0.0, 3.0, math.pi, -2.0], dtype=torch.float64)  # speeds left out
    torch.testing.assert_close(cost(upright), torch.tensor(1.0, dtype=torch.float64))
    car = build(train_config("recipe=mc_pilco", "task=mountaincar"))
    assert factory_keywords(car.make_propagator)["search_cost"] == "widened"
    assert "task_search_cost" not in factory_keywords(car.make_propagator)
    assert cost.absolute_angles  # MC-PILCO's |θ| − π: the cart-pole's default
    wrapped = build(train_config("recipe=mc_pilco", "task.search_reward.angles=wrapped"))
    assert not factory_keywords(wrapped.make_propagator)["task_search_cost"].absolute_angles


def test_a_search_cost_the_task_cannot_give_is_refused_before_any_work():
    with pytest.raises(UserError, match="declares no search_reward"):
        build(train_config("recipe=mc_pilco", "task=mountaincar", "propagation.search_cost=task"))
    with pytest.raises(UserError, match=r"expected_reward=false"):
        build(train_config("recipe=mc_pilco", "propagation.expected_reward=true"))
    with pytest.raises(UserError, match=r"propagation\.search_cost must be one of"):
        build(train_config("recipe=mc_pilco", "propagation.search_cost=tip"))


def test_a_config_stored_with_the_old_envs_package_reads_with_qtl_envs():
    """Before 1.1 the environments were the top-level ``envs``: a stored ``module:EnvId`` of theirs reads as today's."""
    stored = OmegaConf.to_container(tiny_config("task=pendulum"), resolve=True)
    assert stored["task"]["env"]["id"] == "qtl.envs.pendulum_hanging:PendulumHanging-v1"
    stored["task"]["env"]["id"] = "envs.pendulum_hanging:PendulumHanging-v1"
    cfg = typed_groups(OmegaConf.create(stored))
    assert cfg.task.env.id == "qtl.envs.pendulum_hanging:PendulumHanging-v1"
    assert build(cfg).task.env_id == cfg.task.env.id
    assert typed_groups(tiny_config()).task.env.id == "qtl/CartPoleSwingUp-v0"  # a registered id is left alone
