"""The Hydra config tree: every option of every group composes, is typed and instantiates; the schema bites."""

from __future__ import annotations

import dataclasses
import inspect
import itertools
import typing
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.errors import ConfigCompositionException
from hydra.utils import get_object, instantiate
from omegaconf import OmegaConf

import qtl.configs
from qtl.build import build_search
from qtl.config import GROUP_SCHEMAS, TrainConfig, help_text, register_configs
from qtl.features import AngleFeatures
from qtl.policies import Policy
from qtl.task import Task, constructor_parameters

CONFIG_DIR = Path(qtl.configs.__file__).parent
# The kwargs a task file lists although they are the env's defaults: the transfer axes its targets
# change (task.env.pole_mass=2.0 needs the key to exist). Every other listed kwarg must differ.
TRANSFER_AXES = {"cartpole": {"pole_mass"}, "mountaincar": {"power"}}
# Task files whose env needs an optional extra of pyproject.toml: their tests skip only where it does not import.
EXTRAS = {"inverted_pendulum": ("mujoco", "mujoco")}  # task: (module, extra)


def skip_without_extra(task: str) -> None:
    """Skip a test of ``task`` when its env's optional package is not importable, saying which extra installs it."""
    if task in EXTRAS:
        module, extra = EXTRAS[task]
        pytest.importorskip(module, reason=f"task={task} needs the {module!r} package: pip install -e .[{extra}]")


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONFIG_DIR / group).glob("*.yaml"))


def composed(*overrides: str):
    register_configs()
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        return compose(config_name="train", overrides=list(overrides))


GROUP_OPTIONS = [(group, option) for group in GROUP_SCHEMAS for option in options(group)]


def test_groups_have_the_expected_options():
    assert options("task") == [
        "cartpole", "cartpole_dt005", "cartpole_track", "helicopter", "inverted_pendulum", "mountaincar",
        "mountaincar_continuous", "pendulum", "quadcopter",
    ]
    assert "moment_matching" in options("propagation")
    assert {"rbf", "linear"} <= set(options("policy"))
    assert {"lbfgs", "adam"} <= set(options("optimizer"))
    for group, schemas in GROUP_SCHEMAS.items():
        assert set(options(group)) == set(schemas), f"every {group} option has its schema, and only those"


@pytest.mark.parametrize("task", options("task"))
def test_every_task_composes_and_builds_with_one_horizon(task):
    skip_without_extra(task)
    cfg = composed(f"task={task}")
    built = Task.from_config(OmegaConf.to_container(cfg.task, resolve=True))
    assert built.horizon == cfg.task.horizon
    assert built.reward.state_dim == built.state_dim
    assert len(built.state_names) == built.state_dim
    with built.make_env() as env:
        assert env.observation_space.shape == (built.state_dim,)
        # The env truncates where the learner plans: its `horizon` kwarg, else gymnasium's time limit, in env steps.
        limit = getattr(env.unwrapped, "horizon", None) or env.spec.max_episode_steps
        assert limit == built.horizon * built.action_repeat


@pytest.mark.parametrize("task", options("task"))
def test_task_files_list_only_real_kwargs_that_the_task_changes(task):
    skip_without_extra(task)
    env = dict(OmegaConf.load(CONFIG_DIR / "task" / f"{task}.yaml").env)  # the file's own keys (not a base's)
    env.pop("id", None)
    params = constructor_parameters(composed(f"task={task}").task.env.id)
    assert "horizon" not in env, "the horizon is task.horizon, passed to the env"
    for key, value in env.items():
        assert key in params, f"task/{task}.yaml: task.env.{key} is no constructor kwarg of the env"
        default = params[key].default
        same = list(default) == list(value) if isinstance(default, tuple) else default == value
        assert not same or key in TRANSFER_AXES.get(task, set()), f"task/{task}.yaml repeats the default {key}"


def test_quick_aircraft_presets_shorten_the_one_horizon():
    cfg = composed("experiment=aircraft_quick_source")
    built = Task.from_config(OmegaConf.to_container(cfg.task, resolve=True))
    assert built.horizon == 60 and built.env_kwargs["horizon"] == 60


@pytest.mark.parametrize(("policy", "optimizer"), list(itertools.product(options("policy"), options("optimizer"))))
def test_every_policy_and_optimizer_instantiates(policy, optimizer):
    cfg = composed(f"policy={policy}", f"optimizer={optimizer}", "task.policy_size=4")
    task = Task.from_config(OmegaConf.to_container(cfg.task, resolve=True))
    features = AngleFeatures(task.state_dim, task.angle_dims)
    draws = task.start_distribution().sample(10, generator=torch.Generator().manual_seed(0))
    made = instantiate(cfg.policy)(task.feature_dim, task.action_dim, start_features=features(draws))
    assert isinstance(made, Policy)
    assert callable(build_search(cfg.optimizer))


@pytest.mark.parametrize("propagation", options("propagation"))
def test_every_propagation_instantiates_a_partial(propagation):
    assert callable(instantiate(composed(f"propagation={propagation}").propagation))


def test_pole_mass_override_reaches_the_env():
    cfg = composed("task=cartpole", "task.env.pole_mass=2.0")
    task = Task.from_config(OmegaConf.to_container(cfg.task, resolve=True))
    with task.make_env() as env:
        assert env.unwrapped.pole_mass == 2.0


def test_action_repeat_is_a_task_key_that_reaches_the_env():
    assert composed("task=cartpole").task.action_repeat == 1
    cfg = composed("task=cartpole", "task.action_repeat=3")
    task = Task.from_config(OmegaConf.to_container(cfg.task, resolve=True))
    assert task.action_repeat == 3 and task.horizon == cfg.task.horizon
    with task.make_env() as env:
        assert env.unwrapped.horizon == 3 * cfg.task.horizon  # env steps: each of the learner's is held 3 of them


def test_any_other_env_kwarg_is_added_with_a_plus():
    cfg = composed("task=cartpole", "+task.env.friction=0.2")
    task = Task.from_config(OmegaConf.to_container(cfg.task, resolve=True))
    with task.make_env() as env:
        assert env.unwrapped.friction == 0.2


@pytest.mark.parametrize(
    "override",
    ["episdoes=3", "episodes=abc", "task=nosuchtask", "task.horizon=x", "model.restarts=1.5", "task.env.horizon=5",
     "progress=maybe", "task.action_repeat=1.5", "task.action_repeats=2"],
)
def test_schema_rejects_typos_and_wrong_types(override):
    with pytest.raises(ConfigCompositionException):
        composed(override)


@pytest.mark.parametrize(("group", "option"), GROUP_OPTIONS)
def test_every_group_option_is_typed_by_its_schema(group, option):
    cfg = composed(f"{group}={option}")
    assert OmegaConf.get_type(cfg[group]) is GROUP_SCHEMAS[group][option]


@pytest.mark.parametrize(("group", "option"), GROUP_OPTIONS)
def test_every_schema_key_is_a_parameter_of_its_target(group, option):
    node = composed(f"{group}={option}")[group]
    target = get_object(node._target_)
    # a policy search takes its keys as one settings dataclass (qtl.build.build_search), the others as arguments
    settings = getattr(target, "settings_type", None)
    params = ({f.name for f in dataclasses.fields(settings)} if settings is not None
              else inspect.signature(target).parameters)
    keys = [k for k in node if not k.startswith("_")]
    assert set(keys) <= set(params), f"{group}={option}: {set(keys) - set(params)} would not reach the target"


@pytest.mark.parametrize(("group", "option"), GROUP_OPTIONS)
def test_a_typo_inside_any_group_option_fails_at_compose_time(group, option, tmp_path):
    """A preset that misspells a key of the option (here in a YAML file, the way presets set keys) is refused."""
    (tmp_path / "experiment").mkdir()
    (tmp_path / "experiment" / "typo.yaml").write_text(f"# @package _global_\n{group}:\n  restrats: 1\n")
    with pytest.raises(ConfigCompositionException, match="restrats"):
        composed(f"{group}={option}", "experiment=typo", f"hydra.searchpath=[file://{tmp_path}]")
    # ... and a wrong type in any typed key of the option
    hints = typing.get_type_hints(GROUP_SCHEMAS[group][option])
    for f in dataclasses.fields(GROUP_SCHEMAS[group][option]):
        if not f.name.startswith("_") and hints[f.name] in (int, float, bool):
            with pytest.raises(ConfigCompositionException):
                composed(f"{group}={option}", f"{group}.{f.name}=not_a_number")


def test_help_describes_every_key():
    text = help_text()
    assert "  episodes [9]" in text and "learned episodes after them" in text
    assert "rule=bayesian" in text and "rule.evidence_variance [100.0]" in text
    leaves = [f.name for f in dataclasses.fields(TrainConfig) if f.name not in GROUP_SCHEMAS]
    for name in leaves:
        assert f"  {name}" in text


def test_the_fine_cartpole_is_the_cartpole_at_half_the_period_with_the_same_test_in_seconds():
    base, fine = composed("task=cartpole").task, composed("task=cartpole_dt005").task
    assert fine.env.dt == 0.05 and fine.horizon == 2 * base.horizon
    assert fine.success.last_steps == 2 * base.success.last_steps and fine.success.threshold == base.success.threshold
    with Task.from_config(OmegaConf.to_container(base, resolve=True)).make_env() as env:
        assert env.unwrapped.dt == 2 * fine.env.dt  # the env's own default period
    assert {k: v for k, v in fine.items() if k not in ("env", "horizon", "success")} == {
        k: v for k, v in base.items() if k not in ("env", "horizon", "success")}


def test_the_particle_preset_is_the_benchmarked_configuration():
    # docs/benchmarks.md's 5-seed particle benchmark ran these overrides; the preset must resolve to the same config.
    measured = composed("recipe=mc_pilco", "+task.env.dt=0.05", "task.horizon=100", "task.success.last_steps=40",
                        "optimizer.keep=validated", "task.search_reward.angles=absolute")
    preset = composed("task=cartpole_dt005", "recipe=mc_pilco")
    assert OmegaConf.to_container(preset) == OmegaConf.to_container(measured)
