"""The Hydra config tree: every option of every group composes and instantiates; the schema bites."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.errors import ConfigCompositionException
from hydra.utils import instantiate
from omegaconf import OmegaConf

import qtl.configs
from qtl.config import register_configs
from qtl.features import AngleFeatures
from qtl.policies import Policy
from qtl.task import Task

CONFIG_DIR = Path(qtl.configs.__file__).parent


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONFIG_DIR / group).glob("*.yaml"))


def composed(*overrides: str):
    register_configs()
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        return compose(config_name="train", overrides=list(overrides))


def test_groups_have_the_expected_options():
    assert options("task") == ["cartpole", "helicopter", "mountaincar", "quadcopter"]
    assert "moment_matching" in options("propagation")
    assert {"rbf", "linear"} <= set(options("policy"))
    assert {"lbfgs", "adam"} <= set(options("optimizer"))


@pytest.mark.parametrize("task", options("task"))
def test_every_task_composes_and_builds(task):
    cfg = composed(f"task={task}")
    built = Task.from_config(OmegaConf.to_container(cfg.task, resolve=True))
    assert built.horizon == cfg.task.env.horizon
    assert built.reward.state_dim == built.state_dim
    with built.make_env() as env:
        assert env.observation_space.shape == (built.state_dim,)


@pytest.mark.parametrize(("policy", "optimizer"), list(itertools.product(options("policy"), options("optimizer"))))
def test_every_policy_and_optimizer_instantiates(policy, optimizer):
    cfg = composed(f"policy={policy}", f"optimizer={optimizer}", "task.policy_size=4")
    task = Task.from_config(OmegaConf.to_container(cfg.task, resolve=True))
    features = AngleFeatures(task.state_dim, task.angle_dims)
    draws = task.start_distribution().sample(10, generator=torch.Generator().manual_seed(0))
    made = instantiate(cfg.policy)(task.feature_dim, task.action_dim, start_features=features(draws))
    assert isinstance(made, Policy)
    assert callable(instantiate(cfg.optimizer))


@pytest.mark.parametrize("propagation", options("propagation"))
def test_every_propagation_instantiates_a_partial(propagation):
    assert callable(instantiate(composed(f"propagation={propagation}").propagation))


def test_pole_mass_override_reaches_the_env():
    cfg = composed("task=cartpole", "task.env.pole_mass=2.0")
    task = Task.from_config(OmegaConf.to_container(cfg.task, resolve=True))
    with task.make_env() as env:
        assert env.unwrapped.pole_mass == 2.0


@pytest.mark.parametrize(
    "override", ["episdoes=3", "episodes=abc", "task=nosuchtask", "task.horizon=x", "model.restarts=1.5"]
)
def test_schema_rejects_typos_and_wrong_types(override):
    with pytest.raises(ConfigCompositionException):
        composed(override)
