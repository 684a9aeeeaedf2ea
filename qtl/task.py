"""A configured task: its gymnasium env, dimensions, reward, start distribution and success test."""

from __future__ import annotations

import importlib
import inspect
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

import gymnasium
import numpy as np
import torch
from gymnasium.envs.registration import EnvSpec, load_env_creator

import qtl.envs  # noqa: F401  (registers the qtl/ environment ids)
from qtl.constraints import Constraint
from qtl.env_wrappers import ActionRepeat, CenteredAction
from qtl.envs.rewards import SaturatingReward, augment_angles
from qtl.errors import TaskError
from qtl.gaussian import Gaussian

# Floor on the std of a start distribution estimated from the episodes' initial states (``task.start.min_std``).
DEFAULT_START_MIN_STD = 0.01
SEARCH_COST_ANGLES = ("wrapped", "absolute")  # task.search_reward.angles: how δ is taken on angle dims
# task.kinematics.weight: w of T Δq̇ in q_{t+1} = q_t + T q̇_t + w T Δq̇_t; ½ is the trapezoid rule (MC-PILCO's).
TRAPEZOID_WEIGHT = 0.5


class Kinematics(NamedTuple):
    """Which state dimensions are positions and which their velocities, and the control period T in s."""

    positions: tuple[int, ...]  # `K` state indices
    velocities: tuple[int, ...]  # `K`: position k's velocity is velocities[k]
    period: float  # T, the time between two learner steps (held env steps included)
    weight: float = TRAPEZOID_WEIGHT  # w in q_{t+1} = q_t + T q̇_t + w T Δq̇_t: ½ trapezoid, 1 semi-implicit Euler


@dataclass(frozen=True)
class Task:
    """Everything the learner needs to know about a task, checked before any work starts."""

    name: str
    family: str  # tasks of one family share state, action and GP input spaces: transfer stays within one
    env_id: str
    env_kwargs: dict[str, Any]  # what `gymnasium.make` gets besides the id: the time limit (horizon × repeat) included
    horizon: int
    angle_dims: tuple[int, ...]
    state_dim: int
    state_names: tuple[str, ...]  # `D`: the env's ``state_names``, ``task.state_names``, or x[0], x[1], ...
    action_dim: int
    action_bound: np.ndarray  # `F`: the action space (of `make_env`'s env) is [−bound, bound]
    start_mean: np.ndarray | None  # `D`; None when estimated from the episodes' initial states
    start_std: np.ndarray | None  # `D`; None when estimated
    reward: SaturatingReward
    reward_from_env: bool  # the env's own reward is this one (else the env's is ignored)
    success_threshold: float
    success_steps: int
    action_repeat: int = 1  # env steps per learner step: each action is held this long (the horizon counts held steps)
    action_center: np.ndarray | None = None  # `F`: (low + high)/2 of the env's bounds when asymmetric; None: symmetric
    start_estimated: bool = False  # neither the YAML nor the env gives a start distribution: the loop estimates it
    start_min_std: float = DEFAULT_START_MIN_STD  # `σ_0`'s floor when estimated
    reset_options: dict[str, Any] | None = None  # ``env.reset(seed=..., options=...)``; None: the env's default
    search_cost: tuple[np.ndarray, np.ndarray] | None = None  # (target, widths) `D` each, inf width: left out
    search_cost_angles: str = "wrapped"  # δ on its angle dims: wrapped θ − θ*, or absolute |θ| − θ* (raw angle)
    kinematics: Kinematics | None = None  # positions, their velocities and T (particles' speed integration)
    constraints: tuple[Constraint, ...] = ()  # state bounds that end an episode or cost (``qtl.constraints``)

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], env: gymnasium.Env | None = None) -> Task:
        """Build a task from its config node (``task``), checked by ``qtl.config.validate.checked_task`` (not here).

        ``env``: an env of the task to read its spaces and defaults from (None: one is made and closed here).
        """
        env_cfg = dict(cfg["env"])
        env_id = env_cfg.pop("id")
        horizon = int(cfg["horizon"])
        action_repeat = int(cfg.get("action_repeat", 1))
        env_cfg = env_kwargs(env_id, env_cfg, horizon, action_repeat)
        made = gymnasium.make(env_id, **env_cfg) if env is None else None
        opened = env if made is None else made
        try:
            state_dim, action_dim = opened.observation_space.shape[0], opened.action_space.shape[0]
            low, high = opened.action_space.low.astype(float), opened.action_space.high.astype(float)
            start_mean, start_std = _start_distribution(cfg.get("start"), opened.unwrapped, state_dim)
            reward = _reward(cfg.get("reward"), opened.unwrapped, state_dim)
            state_names = _state_names(cfg.get("state_names"), opened.unwrapped, state_dim)
            kinematics = _kinematics(cfg.get("kinematics"), opened.unwrapped, action_repeat)
        finally:
            if made is not None:
                made.close()
        success = cfg["success"]
        reset_options = cfg.get("reset_options")
        return cls(
            name=str(cfg["name"]),
            family=str(cfg.get("family") or env_id),
            env_id=env_id,
            env_kwargs=env_cfg,
            horizon=horizon,
            angle_dims=tuple(int(a) for a in cfg.get("angle_dims", ())),
            state_dim=state_dim,
            state_names=state_names,
            action_dim=action_dim,
            action_bound=(high - low) / 2,
            start_mean=start_mean,
            start_std=start_std,
            reward=reward,
            reward_from_env=cfg.get("reward") is None and action_repeat == 1,  # a held step's env reward is a sum
            success_threshold=float(success["threshold"]),
            success_steps=int(success["last_steps"]),
            action_repeat=action_repeat,
            action_center=None if (low == -high).all() else (low + high) / 2,
            start_estimated=start_mean is None,
            start_min_std=float((cfg.get("start") or {}).get("min_std", DEFAULT_START_MIN_STD)),
            reset_options=None if reset_options is None else dict(reset_options),
            search_cost=_search_cost(cfg.get("search_reward")),
            search_cost_angles=_search_cost_angles(cfg.get("search_reward")),
            kinematics=kinematics,
            constraints=tuple(Constraint.from_config(c) for c in cfg.get("constraints") or ()),
        )

    @property
    def feature_dim(self) -> int:
        """Dimension of the state features (angles as sin, cos) that policy and GP see."""
        return self.state_dim + len(self.angle_dims)

    @property
    def gp_input_dim(self) -> int:
        """Dimension of the GP input [features, action]."""
        return self.feature_dim + self.action_dim

    def make_env(
        self, render_mode: str | None = None, inner: Callable[[gymnasium.Env], gymnasium.Env] | None = None
    ) -> gymnasium.Env:
        """A fresh env of this task: actions in [−action_bound, action_bound], each held ``action_repeat`` env steps.

        ``render_mode``: gymnasium's, for an env that draws (default: none); ``inner``: a wrapper put on the env
        below qtl's own (e.g. a frame recorder that sees every held step).
        """
        kwargs = self.env_kwargs if render_mode is None else {**self.env_kwargs, "render_mode": render_mode}
        env = gymnasium.make(self.env_id, **kwargs)
        if inner is not None:
            env = inner(env)
        if self.action_repeat != 1:
            env = ActionRepeat(env, self.action_repeat)
        return env if self.action_center is None else CenteredAction(env)

    def start_distribution(self, dtype: torch.dtype = torch.float64) -> Gaussian:
        """x_0 ~ N(μ_0, diag(σ_0²)) (Eq. 4), as configured; an estimated start has none (see :meth:`estimate_start`)."""
        if self.start_mean is None or self.start_std is None:
            raise TaskError(f"task {self.name!r} has no configured start distribution: it is estimated from data")
        return diagonal_gaussian(self.start_mean, self.start_std, dtype)

    def distance(self, states: np.ndarray) -> np.ndarray:
        """Distance to the target in the reward's metric, `sqrt((y − y*)ᵀ W (y − y*))`: `T`."""
        y = augment_angles(states, self.reward.angle_dims) - np.asarray(self.reward.target)
        return np.sqrt(np.einsum("...i,ij,...j->...", y, np.asarray(self.reward.weight), y).clip(min=0.0))

    def succeeded(self, states: np.ndarray) -> bool:
        """Whether the last min(``success_steps``, T+1) states of an episode `T+1 x D` are within the threshold.

        Judged on what happened: an episode the env ended early succeeds if it ended within the
        threshold (e.g. at a goal), and fails if it ended away from it (e.g. off the track).
        """
        window = min(self.success_steps, len(states))
        return bool((self.distance(states[len(states) - window :]) <= self.success_threshold).all())

    def first_observation(self, seed: int) -> np.ndarray:
        """x_0 `D` of a fresh env reset with ``seed`` (and ``reset_options``): the first episode's start."""
        with self.make_env() as env:
            obs, _ = env.reset(seed=seed, options=self.reset_options)
        return np.asarray(obs, dtype=float)

    def estimate_start(self, initial_states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """μ_0 `D`, σ_0 `D` fitted to the episodes' initial states `N x D`, σ_0 floored at ``start_min_std``.

        Angles (``angle_dims``) take their circular mean, and their std about it from the angles
        unwrapped to within π of it; the other dimensions their mean and std (ddof 0).
        """
        x0 = np.asarray(initial_states, dtype=float)
        if x0.ndim != 2 or x0.shape[1] != self.state_dim or x0.shape[0] < 1:
            raise ValueError(f"initial states must be `N x {self.state_dim}` with N >= 1, got {x0.shape}")
        mean, std = x0.mean(0), x0.std(0)
        for a in self.angle_dims:
            theta = x0[:, a]
            centre = math.atan2(np.sin(theta).mean(), np.cos(theta).mean())
            offset = np.mod(theta - centre + math.pi, 2 * math.pi) - math.pi  # in [−π, π)
            mean[a], std[a] = centre, math.sqrt(np.mean(offset**2))
        return mean, np.maximum(std, self.start_min_std)


def diagonal_gaussian(mean: np.ndarray, std: np.ndarray, dtype: torch.dtype = torch.float64) -> Gaussian:
    """N(mean `D`, diag(std²) `D x D`) on the CPU."""
    return Gaussian(torch.as_tensor(mean, dtype=dtype), torch.diag(torch.as_tensor(std, dtype=dtype) ** 2))


def constructor_parameters(env_id: str) -> dict[str, inspect.Parameter] | None:
    """The named parameters of ``env_id``'s constructor; None when it takes ``**kwargs`` (any name may be valid)."""
    entry_point = env_spec(env_id).entry_point
    try:
        creator = load_env_creator(entry_point) if isinstance(entry_point, str) else entry_point
    except (gymnasium.error.DependencyNotInstalled, ImportError) as err:
        mujoco = "mujoco" in str(entry_point)
        extra = " (qtl's extra for gymnasium's MuJoCo envs: pip install -e .[mujoco])" if mujoco else ""
        raise TaskError(f"cannot load task.env.id={env_id!r}, a package it needs is missing: {err}{extra}") from err
    params = inspect.signature(creator).parameters
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values()):
        return None
    return dict(params)


def env_settings(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """Every setting a task config (``task``) gives its env, the constructor's defaults filled in: what the env is.

    Two task configs that list different kwargs but make the same env give equal settings.
    """
    env_cfg = dict(cfg["env"])
    env_id = env_cfg.pop("id", None)
    if not env_id:
        raise TaskError("task.env.id is missing: name a registered gymnasium env id")
    action_repeat = action_repeat_of(cfg)
    params = constructor_parameters(env_id) or {}
    defaults = {n: p.default for n, p in params.items() if p.default is not inspect.Parameter.empty}
    settings = {"id": env_id, **defaults, **env_kwargs(env_id, env_cfg, int(cfg["horizon"]), action_repeat)}
    if action_repeat != 1:  # a dotted key: no constructor kwarg (an env's own ``action_repeat``) can clash with it
        settings["task.action_repeat"] = action_repeat
    return {key: _plain(value) for key, value in settings.items()}


def env_spec(env_id: str) -> EnvSpec:
    """The registered spec of ``env_id``, importing ``module`` first for gymnasium's ``"module:EnvId"`` form."""
    module, _, name = env_id.rpartition(":")
    if module:
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as err:
            missing = err.name or module
            raise TaskError(
                f"cannot import module {missing!r} for task.env.id={env_id!r}: pip install {missing.split('.')[0]} "
                "(or the package that provides it)"
            ) from err
        except ImportError as err:
            raise TaskError(f"cannot import module {module!r} for task.env.id={env_id!r}: {err}") from err
    try:
        return gymnasium.spec(name)
    except gymnasium.error.Error as err:
        registers = f" (module {module!r} imports but does not register {name!r})" if module else ""
        raise TaskError(f"cannot make task.env.id={env_id!r}: {err}{registers}") from err


def _plain(value: Any) -> Any:
    """Tuples as lists, recursively (constructor defaults against config lists)."""
    return [_plain(v) for v in value] if isinstance(value, (tuple, list)) else value


def env_kwargs(env_id: str, env_cfg: dict[str, Any], horizon: int, action_repeat: int = 1) -> dict[str, Any]:
    """``env_cfg`` plus the one horizon: the env's ``horizon`` kwarg if it has one, else gymnasium's time limit.

    The learner's ``horizon`` steps are ``horizon × action_repeat`` steps of the env (an ``env_cfg`` horizon that
    disagrees is refused by ``qtl.config.validate.checked_task``; this one wins).
    """
    params = constructor_parameters(env_id)
    if params is not None and "horizon" in params:
        return {**env_cfg, "horizon": horizon * action_repeat}
    return {**env_cfg, "max_episode_steps": horizon * action_repeat}


def action_repeat_of(cfg: Mapping[str, Any]) -> int:
    """``task.action_repeat`` (default 1), checked: a whole number of env steps >= 1."""
    repeat = cfg.get("action_repeat", 1)
    if isinstance(repeat, bool) or not isinstance(repeat, (int, np.integer)) or repeat < 1:
        raise TaskError(
            f"task.action_repeat must be a whole number of env steps >= 1 (1: every env step), got {repeat!r}"
        )
    return int(repeat)


def _state_names(names: Sequence[str] | None, env: gymnasium.Env, state_dim: int) -> tuple[str, ...]:
    """``task.state_names``, else the env's ``state_names``, else ``x[0]``, ``x[1]``, ...: `D`."""
    names = getattr(env, "state_names", None) if names is None else names
    if names is None:
        return tuple(f"x[{d}]" for d in range(state_dim))
    return tuple(str(n) for n in names)


def _start_distribution(
    cfg: Mapping[str, Any] | None, env: gymnasium.Env, state_dim: int
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """μ_0 `D`, σ_0 `D` from ``task.start``, else the env's ``start_mean``/``start_std``; (None, None): estimate them.

    One of mean and std given without the other is completed by the env's.
    """
    mean = None if cfg is None else cfg.get("mean")
    std = None if cfg is None else cfg.get("std")
    mean = getattr(env, "start_mean", None) if mean is None else mean
    std = getattr(env, "start_std", None) if std is None else std
    if mean is None and std is None:
        return None, None
    mean = np.broadcast_to(np.asarray(mean, dtype=float), (state_dim,)).copy()
    std = np.broadcast_to(np.asarray(std, dtype=float), (state_dim,)).copy()
    return mean, std


def _reward(cfg: Mapping[str, Any] | None, env: gymnasium.Env, state_dim: int) -> SaturatingReward:
    """``task.reward`` (integers read as floats), else the env's ``reward_spec``."""
    if cfg is None:
        return env.reward_spec
    return SaturatingReward(
        state_dim=state_dim,
        angle_dims=tuple(cfg["angle_dims"]),
        target=_floats(cfg["target"]),
        weight=[_floats(row) for row in cfg["weight"]],
        width=float(cfg["width"]),
    )


def _floats(values: Sequence[Any]) -> list[float]:
    return [float(v) for v in values]


def _search_cost(cfg: Mapping[str, Any] | None) -> tuple[np.ndarray, np.ndarray] | None:
    """``task.search_reward`` as (target, widths) `D` each (null entries: width inf, left out)."""
    if cfg is None:
        return None
    target, widths = list(cfg.get("target") or []), list(cfg.get("widths") or [])
    used = [w is not None for w in widths]
    return (np.array([float(t) if u else 0.0 for u, t in zip(used, target, strict=True)]),
            np.array([float(w) if u else math.inf for u, w in zip(used, widths, strict=True)]))


def _search_cost_angles(cfg: Mapping[str, Any] | None) -> str:
    """``task.search_reward.angles``: ``wrapped`` (the default) or ``absolute``."""
    return "wrapped" if cfg is None else str(cfg.get("angles") or "wrapped")


def _kinematics(cfg: Mapping[str, Any] | None, env: gymnasium.Env, action_repeat: int) -> Kinematics | None:
    """``task.kinematics``, its period T the given one or the env's ``dt`` × ``action_repeat``; None: none declared."""
    if not declares_kinematics(cfg):
        return None
    positions = tuple(int(p) for p in cfg.get("positions") or ())
    velocities = tuple(int(v) for v in cfg.get("velocities") or ())
    period = cfg.get("period")
    weight = cfg.get("weight")
    return Kinematics(positions, velocities, float(env.dt) * action_repeat if period is None else float(period),
                      TRAPEZOID_WEIGHT if weight is None else float(weight))


def declares_kinematics(cfg: Mapping[str, Any] | None) -> bool:
    """Whether a ``task.kinematics`` node declares any: null and the empty node (no positions, no velocities) do not."""
    return cfg is not None and bool(cfg.get("positions") or cfg.get("velocities"))


def check_kinematics(
    state_dim: int, positions: Sequence[int], velocities: Sequence[int], period: float,
    weight: float = TRAPEZOID_WEIGHT,
) -> None:
    """Positions and velocities paired, distinct, disjoint, below ``state_dim``; T > 0; 0 ≤ w ≤ 1: else a TaskError."""
    if not 0.0 <= weight <= 1.0:
        raise TaskError(f"task.kinematics.weight must be in [0, 1] (½: the trapezoid rule, 1: semi-implicit Euler), "
                        f"got {weight}")
    if not positions or len(positions) != len(velocities):
        raise TaskError(f"task.kinematics needs as many velocities as positions, at least one: got positions "
                        f"{list(positions)}, velocities {list(velocities)}")
    both = [*positions, *velocities]
    if len(set(both)) != len(both) or not all(0 <= d < state_dim for d in both):
        raise TaskError(f"task.kinematics positions {list(positions)} and velocities {list(velocities)} must be "
                        f"distinct state indices below {state_dim}")
    if not (0 < period < math.inf):
        raise TaskError(f"task.kinematics.period must be a control period > 0 in seconds, got {period}")
