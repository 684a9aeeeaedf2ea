"""Every value check Hydra cannot make: the budget, the group keys, the task and the components' settings.

Each raises a one-line :class:`~qtl.errors.UserError` (a :class:`~qtl.errors.TaskError` for the task) that says
what to fix, before any work. :func:`checked_task` checks a task config in a fixed order, so that the same bad
input always gives the same line, and then builds the :class:`~qtl.task.Task` (which checks nothing itself).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import gymnasium
import numpy as np
from omegaconf import DictConfig
from torch import nn

from qtl.config.groups import GROUP_SCHEMAS, SCHEMA_BY_TARGET
from qtl.constraints import CONSTRAINT_KINDS
from qtl.envs.rewards import SaturatingReward
from qtl.errors import TaskError, TransferError, UserError
from qtl.task import (
    DEFAULT_START_MIN_STD,
    SEARCH_COST_ANGLES,
    TRAPEZOID_WEIGHT,
    Task,
    action_repeat_of,
    check_kinematics,
    declares_kinematics,
    env_kwargs,
)
from qtl.transfer.compliance import BANDWIDTHS, COMPLIANCES, DEFAULT_COMPLIANCE
from qtl.transfer.plan import SELECT_MODES
from qtl.transfer.rules import HyperparameterRule
from qtl.transfer.samples import SAMPLE_MODES

FLATTEN_HINT = (
    "flatten it in your own env registration (gymnasium.wrappers.FlattenObservation for observations) "
    "or give a 1-D Box"
)


# -- the run ------------------------------------------------------------------------------------------


def check_budget(cfg: DictConfig) -> None:
    """Episode counts a run can learn from; a one-line :class:`UserError` otherwise."""
    if cfg.random_episodes < 1:
        raise UserError(
            f"random_episodes={cfg.random_episodes}: the first model needs data, so random_episodes must be >= 1 "
            "(the initial episodes apply random actions, or π(ψ_s) with transfer.policy=true)"
        )
    if cfg.episodes < 0:
        raise UserError(f"episodes={cfg.episodes}: the learned episodes after the initial ones must be >= 0")
    if cfg.keep_checkpoints < 0:
        raise UserError(f"keep_checkpoints={cfg.keep_checkpoints}: keep the newest N >= 1 checkpoints, or 0 for all")


def check_group_keys(cfg: DictConfig) -> None:
    """Every key of a group node is a key of its option's schema (``+group.key=...`` gets past Hydra's check)."""
    for group in GROUP_SCHEMAS:
        node = cfg.get(group)
        schema = None if node is None else SCHEMA_BY_TARGET.get(node.get("_target_"))
        if schema is None:
            continue
        known = {f.name for f in dataclasses.fields(schema)}
        unknown = sorted(set(node) - known)
        if unknown:
            raise UserError(
                f"{group}.{unknown[0]} is no key of {group} {node._target_}: its keys are "
                f"{sorted(k for k in known if not k.startswith('_'))}"
            )


def check_dropout(cfg: DictConfig) -> None:
    """Policy dropout needs particles and a policy that can drop its basis functions: a UserError otherwise."""
    if float(cfg.optimizer.get("dropout", 0.0) or 0.0) == 0.0:
        return
    if not str(cfg.propagation._target_).endswith("Particles"):
        raise UserError("optimizer.dropout > 0 needs propagation=particles (moment matching has no dropout): "
                        "set optimizer.dropout=0 or propagation=particles")
    if not str(cfg.policy._target_).endswith("rbf_network_policy"):
        raise UserError("optimizer.dropout > 0 needs policy=rbf_network (the only policy with dropout): "
                        "set policy=rbf_network or optimizer.dropout=0")


def check_lr_scales(search: object, initial_policy: Callable[[], nn.Module]) -> None:
    """``optimizer.lr_scales`` must name parts of the configured policy's ψ: a UserError otherwise."""
    scales = getattr(search, "lr_scales", None)
    if not scales:
        return
    named = dict(initial_policy().named_parameters())
    try:
        search.param_groups(named, 1.0)  # type: ignore[attr-defined]
    except ValueError as err:
        raise UserError(str(err)) from None


# -- transfer -------------------------------------------------------------------------------------------


def check_transfer(cfg: Mapping[str, Any], rule: HyperparameterRule) -> None:
    """The ``transfer`` node agrees with itself and with ``rule``: a one-line TransferError otherwise, before any work.

    The source run itself (its files, task family and shapes) is checked where it is loaded
    (:class:`qtl.transfer.SourceRun`).
    """
    transfer_theta = bool(cfg.get("hyperparameters", True))
    min_compliance, temperature = cfg.get("min_compliance"), cfg.get("compliance_temperature")
    _check_source_value(cfg.get("source"))
    select, initial_policy = str(cfg.get("select") or "compliance"), cfg.get("initial_policy")
    if select not in SELECT_MODES:
        raise TransferError(f"transfer.select must be one of {', '.join(SELECT_MODES)}, got {select!r}")
    if initial_policy is not None and (not isinstance(initial_policy, str) or not initial_policy):
        raise TransferError(f"transfer.initial_policy must be a source run directory, got {initial_policy!r}")
    samples, max_samples = str(cfg.get("samples") or "none"), cfg.get("max_source_samples", 1)
    if samples not in SAMPLE_MODES:
        raise TransferError(f"transfer.samples must be one of {', '.join(SAMPLE_MODES)}, got {samples!r}")
    if isinstance(max_samples, bool) or not isinstance(max_samples, int) or max_samples < 1:
        raise TransferError(f"transfer.max_source_samples must be an integer >= 1, got {max_samples!r}")
    if cfg.get("source") is None:
        if samples != "none":
            raise TransferError("transfer.samples=relevance takes the source's tuples: give transfer.source=<run dir>")
        if initial_policy is not None:
            raise TransferError("transfer.initial_policy names one of the sources: give transfer.source=<run dir(s)>")
        if rule.uses_source:
            raise TransferError(f"rule={rule.name} starts from the source's θ_s: give transfer.source=<run dir>")
        if bool(cfg.get("policy", False)):
            raise TransferError("transfer.policy=true needs a source run: give transfer.source=<run dir>")
        if min_compliance is not None:
            raise TransferError("transfer.min_compliance needs a source run: give transfer.source=<run dir>")
    else:
        if transfer_theta and not rule.uses_source:
            raise TransferError(
                "transfer.hyperparameters=true but rule=none ignores θ_s: choose rule=free|forgetting|bayesian "
                "(or an approach=... preset), or set transfer.hyperparameters=false"
            )
        if rule.uses_source and not transfer_theta:
            raise TransferError(f"rule={rule.name} updates θ_s, but transfer.hyperparameters=false")
    if min_compliance is not None and not 0.0 <= float(min_compliance) <= 1.0:
        raise TransferError(f"transfer.min_compliance must be in [0, 1], got {min_compliance}")
    if temperature is not None and not float(temperature) > 0:
        raise TransferError(f"transfer.compliance_temperature must be > 0, got {temperature}")
    resolution = float(cfg.get("compliance_resolution") or 0.0)
    if not (math.isfinite(resolution) and resolution >= 0):
        raise TransferError(f"transfer.compliance_resolution must be >= 0, got {resolution}")
    name, bandwidth = str(cfg.get("compliance") or DEFAULT_COMPLIANCE), str(cfg.get("compliance_bandwidth") or "scott")
    if name not in COMPLIANCES:
        raise TransferError(f"transfer.compliance must be one of {', '.join(sorted(COMPLIANCES))}, got {name!r}")
    if bandwidth not in BANDWIDTHS:
        raise TransferError(f"transfer.compliance_bandwidth must be one of {', '.join(BANDWIDTHS)}, got {bandwidth!r}")
    if name == "kernel" and temperature is not None:
        raise TransferError("transfer.compliance_temperature tempers the likelihood ratio only: unset it, or set "
                            "transfer.compliance=likelihood_ratio")


def _check_source_value(source: Any) -> None:
    """``transfer.source`` is null, a directory, or a non-empty list of distinct directories: a TransferError else."""
    if source is None or (isinstance(source, str) and source):
        return
    if isinstance(source, Sequence) and not isinstance(source, str):
        if not source:
            raise TransferError("transfer.source=[] names no source run: give one run directory or several")
        if bad := [s for s in source if not isinstance(s, str) or not s]:
            raise TransferError(f"transfer.source: every entry must be a run directory, got {bad[0]!r}")
        if len(set(source)) != len(source):
            raise TransferError(f"transfer.source names a run twice: {list(source)}")
        return
    raise TransferError(f"transfer.source must be a run directory, a list of them or a directory holding them, "
                        f"got {source!r}")


# -- the task -------------------------------------------------------------------------------------------


def checked_task(cfg: Mapping[str, Any]) -> Task:
    """The task of a config node (``task``), every value checked first: a one-line TaskError for the first bad one.

    Makes one env to read its spaces, and builds the task with it.
    """
    env_cfg = dict(cfg["env"])
    env_id = env_cfg.pop("id", None)
    if not env_id:
        raise TaskError("task.env.id is missing: name a registered gymnasium env id")
    horizon = int(cfg["horizon"])
    if horizon <= 0:
        raise TaskError(f"task.horizon must be a positive number of steps, got {horizon}")
    action_repeat = action_repeat_of(cfg)
    success = cfg["success"]
    if int(success["last_steps"]) > horizon:
        raise TaskError(
            f"task.success.last_steps={success['last_steps']} is longer than task.horizon={horizon}: "
            f"set task.success.last_steps to at most {horizon}"
        )
    if "horizon" in env_cfg and int(env_cfg["horizon"]) != horizon:
        raise TaskError(
            f"task.env.horizon={env_cfg['horizon']} disagrees with task.horizon={horizon}: set task.horizon only "
            "(it is the env's horizon too)"
        )
    kwargs = env_kwargs(env_id, env_cfg, horizon, action_repeat)
    try:
        env = gymnasium.make(env_id, **kwargs)
    except gymnasium.error.Error as err:
        raise TaskError(f"cannot make task.env.id={env_id!r}: {err}") from err
    except (TypeError, ValueError) as err:
        raise TaskError(f"bad constructor kwargs for {env_id!r} under task.env: {err}") from err
    try:
        check_spaces(env_id, env.observation_space, env.action_space)
        state_dim = env.observation_space.shape[0]
        angle_dims = [int(a) for a in cfg.get("angle_dims", ())]
        if any(not 0 <= a < state_dim for a in angle_dims) or len(set(angle_dims)) != len(angle_dims):
            raise TaskError(f"task.angle_dims {angle_dims} must be distinct indices below {state_dim}")
        _check_start(cfg.get("start"), env.unwrapped, state_dim)
        _check_reward(cfg.get("reward"), env.unwrapped, env_id, state_dim)
        _check_state_names(cfg.get("state_names"), env.unwrapped, state_dim)
        _check_kinematics(cfg.get("kinematics"), env.unwrapped, state_dim, action_repeat)
        _check_constraints(cfg.get("constraints"), state_dim)
        _check_rest(cfg, horizon, state_dim)
        return Task.from_config(cfg, env)
    finally:
        env.close()


def _check_rest(cfg: Mapping[str, Any], horizon: int, state_dim: int) -> None:
    """Success test, start floor, reset options and search reward of a task config, in that order."""
    success = cfg["success"]
    if float(success["threshold"]) <= 0 or not 1 <= int(success["last_steps"]) <= horizon:
        raise TaskError(
            f"task.success needs threshold > 0 and 1 <= last_steps <= horizon ({horizon}), got {dict(success)}"
        )
    start_min_std = float((cfg.get("start") or {}).get("min_std", DEFAULT_START_MIN_STD))
    if not (math.isfinite(start_min_std) and start_min_std > 0):
        raise TaskError(f"task.start.min_std must be a positive std, got {start_min_std}")
    reset_options = cfg.get("reset_options")
    if reset_options is not None and not isinstance(reset_options, Mapping):
        raise TaskError(f"task.reset_options must be a mapping (the env's reset options), got {reset_options!r}")
    _check_search_reward(cfg.get("search_reward"), state_dim)


def check_spaces(env_id: str, obs_space: gymnasium.Space, act_space: gymnasium.Space) -> None:
    """Refuse, in one line that says why and what to do, spaces qtl cannot learn with: 1-D Box spaces only."""
    spaces = gymnasium.spaces
    for what, space in (("action", act_space), ("observation", obs_space)):
        if isinstance(space, (spaces.Dict, spaces.Tuple)):
            raise TaskError(f"{env_id} has a {type(space).__name__} {what} space {space}: {FLATTEN_HINT}")
    if isinstance(act_space, (spaces.Discrete, spaces.MultiDiscrete, spaces.MultiBinary)) or (
        isinstance(act_space, spaces.Box) and not np.issubdtype(act_space.dtype, np.floating)
    ):
        raise TaskError(
            f"{env_id} has the action space {act_space}: qtl needs continuous actions (a 1-D Box): "
            "PILCO's policy is a continuous map"
        )
    if isinstance(obs_space, spaces.Box) and (len(obs_space.shape) > 1 or obs_space.dtype == np.uint8):
        raise TaskError(
            f"{env_id} observes images ({obs_space}): pixels are not states; qtl models states with a GP: "
            "give the env a 1-D Box observation of its state"
        )
    for what, space in (("action", act_space), ("observation", obs_space)):
        if not isinstance(space, spaces.Box) or len(space.shape) != 1:
            raise TaskError(f"{env_id} must have a 1-D Box {what} space, it has {space}")
    low, high = act_space.low.astype(float), act_space.high.astype(float)
    if not (np.isfinite(low).all() and np.isfinite(high).all() and (high > low).all()):
        raise TaskError(
            f"{env_id} must have finite action bounds low < high, it has [{low}, {high}]: "
            "register the env with the bounded action range it accepts"
        )


def _check_start(cfg: Mapping[str, Any] | None, env: gymnasium.Env, state_dim: int) -> None:
    """``task.start`` (or the env's ``start_mean``/``start_std``): both or neither, finite, std >= 0."""
    mean = None if cfg is None else cfg.get("mean")
    std = None if cfg is None else cfg.get("std")
    mean = getattr(env, "start_mean", None) if mean is None else mean
    std = getattr(env, "start_std", None) if std is None else std
    if mean is None and std is None:
        return
    if mean is None or std is None:
        given, missing = ("mean", "std") if std is None else ("std", "mean")
        raise TaskError(f"task.start.{given} is set but the env exposes no start_{missing}: set task.start.{missing} "
                        f"too, or neither (the start distribution is then estimated from the episodes)")
    mean = np.broadcast_to(np.asarray(mean, dtype=float), (state_dim,))
    std = np.broadcast_to(np.asarray(std, dtype=float), (state_dim,))
    if not (np.isfinite(mean).all() and np.isfinite(std).all() and (std >= 0).all()):
        raise TaskError(f"start distribution must be finite with std >= 0, got mean {mean}, std {std}")


def check_reward_weight(weight: Any) -> None:
    """``task.reward.weight`` is a matrix of numbers (rows of ints or floats); a one-line TaskError otherwise."""
    rows = weight if isinstance(weight, Sequence) and not isinstance(weight, str) else None
    if rows is None or not all(
        isinstance(row, Sequence) and not isinstance(row, str)
        and all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in row)
        for row in rows
    ):
        raise TaskError(f"task.reward.weight must be a matrix of numbers (a list of rows), got {weight!r}")


def _check_reward(cfg: Mapping[str, Any] | None, env: gymnasium.Env, env_id: str, state_dim: int) -> None:
    """``task.reward`` a valid saturating reward, else the env's ``reward_spec`` for states of ``state_dim``."""
    if cfg is not None:
        if "weight" in cfg:
            check_reward_weight(cfg["weight"])
        try:
            SaturatingReward(
                state_dim=state_dim,
                angle_dims=tuple(cfg["angle_dims"]),
                target=[float(v) for v in cfg["target"]],
                weight=[[float(v) for v in row] for row in cfg["weight"]],
                width=float(cfg["width"]),
            )
        except (KeyError, ValueError) as err:
            raise TaskError(f"task.reward is not a valid saturating reward: {err}") from err
        return
    spec = getattr(env, "reward_spec", None)
    if spec is None:
        raise TaskError(f"{env_id} has no reward_spec: describe its reward under task.reward")
    if spec.state_dim != state_dim:
        raise TaskError(f"{env_id}.reward_spec is for {spec.state_dim}-D states, observations are {state_dim}-D")


def _check_state_names(names: Sequence[str] | None, env: gymnasium.Env, state_dim: int) -> None:
    """``task.state_names`` (else the env's) name every state dimension."""
    names = getattr(env, "state_names", None) if names is None else names
    if names is not None and len(names) != state_dim:
        raise TaskError(f"task.state_names names {len(names)} dimensions, the state has {state_dim}: {list(names)}")


def _check_kinematics(cfg: Mapping[str, Any] | None, env: gymnasium.Env, state_dim: int, action_repeat: int) -> None:
    """``task.kinematics``: paired indices, a weight w and a period, given or the env's ``dt`` × ``action_repeat``."""
    if not declares_kinematics(cfg):
        return
    positions = tuple(int(p) for p in cfg.get("positions") or ())
    velocities = tuple(int(v) for v in cfg.get("velocities") or ())
    period = cfg.get("period")
    if period is None:
        dt = getattr(env, "dt", None)
        if dt is None:
            raise TaskError("task.kinematics.period is not set and the env has no dt: set task.kinematics.period "
                            "to the control period in seconds")
        period = float(dt) * action_repeat
    weight = TRAPEZOID_WEIGHT if cfg.get("weight") is None else float(cfg["weight"])
    check_kinematics(state_dim, positions, velocities, float(period), weight)


CONSTRAINT_KEYS = ("dim", "low", "high", "kind", "weight")


def _check_constraints(cfg: Sequence[Any] | None, state_dim: int) -> None:
    """``task.constraints``: each entry a known dim, a bound or two (low < high), a known kind and its weight."""
    if cfg is None:
        return
    if isinstance(cfg, (str, Mapping)) or not isinstance(cfg, Sequence):
        raise TaskError(f"task.constraints must be a list of bounds ({{dim, low, high, kind, weight}}), got {cfg!r}")
    seen: set[tuple[int, str]] = set()
    for i, entry in enumerate(cfg):
        key = f"task.constraints[{i}]"
        if not isinstance(entry, Mapping):
            raise TaskError(f"{key} must be a mapping {{dim, low, high, kind, weight}}, got {entry!r}")
        unknown = sorted(set(entry) - set(CONSTRAINT_KEYS))
        if unknown:
            raise TaskError(f"{key}.{unknown[0]} is no key of a constraint: its keys are {', '.join(CONSTRAINT_KEYS)}")
        dim = entry.get("dim")
        if isinstance(dim, bool) or not isinstance(dim, numbers.Integral) or not 0 <= dim < state_dim:
            raise TaskError(f"{key}.dim must be a state dimension in 0..{state_dim - 1}, got {dim!r}")
        low, high = entry.get("low"), entry.get("high")
        for side, value in (("low", low), ("high", high)):
            if value is not None and (isinstance(value, bool) or not isinstance(value, numbers.Real)
                                      or math.isnan(value)):
                raise TaskError(f"{key}.{side} must be a number or null (unbounded), got {value!r}")
        if low is None and high is None:
            raise TaskError(f"{key} bounds nothing: give {key}.low, {key}.high or both")
        if low is not None and high is not None and not low < high:
            raise TaskError(f"{key}.low={low} must be below {key}.high={high}")
        kind = entry.get("kind", "terminate")
        if kind not in CONSTRAINT_KINDS:
            raise TaskError(f"{key}.kind must be one of {', '.join(CONSTRAINT_KINDS)}, got {kind!r}")
        weight = entry.get("weight") or 0.0
        if isinstance(weight, bool) or not isinstance(weight, numbers.Real) or not math.isfinite(weight):
            raise TaskError(f"{key}.weight must be a finite number, got {weight!r}")
        if kind == "penalty" and not weight > 0:
            raise TaskError(f"{key}.weight must be > 0 for kind=penalty (the cost per step of 1 − p_t), got {weight}")
        if kind == "terminate" and weight != 0:
            raise TaskError(f"{key}.weight must be 0 for kind=terminate (termination costs the lost reward), "
                            f"got {weight}")
        if (int(dim), kind) in seen:
            raise TaskError(f"{key} bounds dimension {dim} ({kind}) a second time: give one entry with both bounds")
        seen.add((int(dim), kind))


def _check_search_reward(cfg: Mapping[str, Any] | None, state_dim: int) -> None:
    """``task.search_reward``: target and widths of ``state_dim`` entries, finite where used, a known ``angles``."""
    if cfg is not None:
        target, widths = list(cfg.get("target") or []), list(cfg.get("widths") or [])
        if len(target) != state_dim or len(widths) != state_dim:
            raise TaskError(f"task.search_reward needs target and widths of {state_dim} entries each (null: left "
                            f"out), got {len(target)} and {len(widths)}")
        used = [w is not None for w in widths]
        if not any(used) or any(u and (t is None or float(w) <= 0 or not math.isfinite(float(w)))
                                for u, t, w in zip(used, target, widths, strict=True)):
            raise TaskError(f"task.search_reward needs a finite target and a finite width > 0 on every dimension it "
                            f"uses, and at least one: got target {target}, widths {widths}")
    angles = "wrapped" if cfg is None else str(cfg.get("angles") or "wrapped")
    if angles not in SEARCH_COST_ANGLES:
        raise TaskError(f"task.search_reward.angles must be one of {', '.join(SEARCH_COST_ANGLES)}, got {angles!r}")
