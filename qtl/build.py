"""One ``build(cfg)``: the parts of Algorithm 1 made from the config and checked, for the loop and every script."""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch
from hydra.errors import InstantiationException
from hydra.utils import get_class, instantiate
from omegaconf import DictConfig, OmegaConf
from torch import Tensor, nn

from qtl.config.validate import check_dropout, check_lr_scales, check_transfer, checked_task
from qtl.data import TransitionDataset, gp_training_pairs
from qtl.episodes import Actor, policy_actor
from qtl.errors import UserError
from qtl.features import AngleFeatures
from qtl.gaussian import Gaussian
from qtl.kernels import Engine
from qtl.models import DynamicsGP, GPHyperparameters, ModelFit, PreviousFit
from qtl.policies import Policy, SquashedPolicy
from qtl.policy_search import SearchResult
from qtl.propagation import PropagatorFactory
from qtl.propagation.integration import modelled_outputs
from qtl.propagation.objective import is_shaped
from qtl.rewards import AngleDistanceReward, ExpectedSaturatingReward
from qtl.seeding import ENV_STREAM, POLICY_INIT_STREAM, derive_seed, torch_generator
from qtl.task import Task, diagonal_gaussian
from qtl.transfer.plan import TransferPlan
from qtl.transfer.samples import WeightedSamples

DTYPES = {"float64": torch.float64, "float32": torch.float32}
# Draws from the start distribution from which the initial support points are taken.
START_DRAWS = 1000


class PolicySearch(Protocol):
    """What ``build_search(cfg.optimizer)`` gives: ψ improved in place to maximise the objective (lines 6-9)."""

    def __call__(
        self,
        policy: nn.Module,
        objective: Callable[[], Tensor],
        *,
        generator: torch.Generator | None = None,
        tick: Callable[[], None] = ...,
    ) -> SearchResult:
        """Maximise ``objective()`` over ``policy.parameters()``; leave the best ψ in ``policy``."""
        ...


class PolicyFactory(Protocol):
    """What ``instantiate(cfg.policy)`` gives (a ``_partial_`` config): the unsquashed initial policy."""

    def __call__(
        self,
        input_dim: int,
        output_dim: int,
        *,
        start_features: Tensor,
        features: AngleFeatures | None = None,
        generator: torch.Generator | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> Policy:
        """π(ψ_0) on features `input_dim`, actions `output_dim`, around ``start_features`` `S x input_dim`.

        ``features``: the state-to-feature map, for a policy that spreads itself over the state space.
        """
        ...


@dataclass(frozen=True)
class Parts:
    """What Algorithm 1 works with, made from the config: the task, its maths, and the swappable components."""

    seed: int
    dtype: torch.dtype
    device: torch.device
    task: Task
    features: AngleFeatures
    reward: ExpectedSaturatingReward
    start: Gaussian  # N(μ_0, Σ_0) on ``device``; estimated tasks: x_0 of the first episode, σ_0 the floor
    model: ModelFit  # the ``model`` group: which GP, and its evidence maximisation
    make_propagator: PropagatorFactory  # the ``propagation`` group
    search: PolicySearch  # the ``optimizer`` group
    make_policy: PolicyFactory  # the ``policy`` group
    engine: Engine  # the code that computes moments and exp sums (``kernels.*``, resolved), in every propagator
    search_reward: str = "task"  # what the policy search scores, by name (:func:`search_reward_name`)
    outputs: tuple[int, ...] | None = None  # the state dimensions the GP models (propagation.integration); None: all

    @property
    def modelled(self) -> tuple[int, ...]:
        """The state dimensions the dynamics GP models: all but the positions under speed integration, else all."""
        return tuple(range(self.task.state_dim)) if self.outputs is None else self.outputs

    @property
    def kernel_backend(self) -> str:
        """The exp sums' code in effect: ``native`` or ``torch`` (``kernels.backend``, resolved)."""
        return self.engine.exp_sums

    def initial_policy(self) -> SquashedPolicy:
        """π(ψ_0) as PILCO starts it (line 1): the configured policy around the start state, squashed, on the device."""
        generator = torch_generator(self.seed, 0, POLICY_INIT_STREAM)
        draws = self.start.to(device="cpu").sample(START_DRAWS, generator=generator)  # START_DRAWS x D
        inner = self.make_policy(self.task.feature_dim, self.task.action_dim, start_features=self.features(draws),
                                 features=self.features, generator=generator, dtype=self.dtype)
        return SquashedPolicy(inner, torch.as_tensor(self.task.action_bound, dtype=self.dtype)).to(self.device)

    def gp_data(self, data: TransitionDataset) -> tuple[Tensor, Tensor]:
        """The GP's training pairs of ``data``: inputs `n x (F+U)`, Δ of the modelled outputs `n x E`, on the device."""
        inputs, targets = gp_training_pairs(data, self.features, self.dtype, self.device)
        outputs = self.modelled
        if outputs != tuple(range(targets.shape[-1])):
            targets = targets[:, list(outputs)]
        return inputs, targets

    def fit_dynamics(
        self, data: TransitionDataset, generator: torch.Generator, start: GPHyperparameters | None = None,
        previous: PreviousFit | None = None, samples: WeightedSamples | None = None,
    ) -> DynamicsGP:
        """θ_p by evidence maximisation on all tuples (line 12), from ``start`` or PILCO's heuristic, on the device.

        The GP is fitted on the modelled outputs' Δ only (:attr:`modelled`). ``previous``: the last episode's fit,
        where ``model.warm_start`` starts from (ignored when off). ``samples``: source tuples after the target's,
        with noise σ_ε² / w at the θ they were judged at (``transfer.samples=relevance``, :mod:`qtl.transfer.samples`).
        """
        inputs, targets = self.gp_data(data)
        extra = None
        if samples is not None:  # the target's tuples first, with no extra noise
            extra = torch.cat([torch.zeros_like(targets), samples.extra_noise.to(targets)])
            inputs, targets = torch.cat([inputs, samples.inputs.to(inputs)]), torch.cat([targets,
                                                                                         samples.targets.to(targets)])
        return self.model.fit(inputs, targets, start=start, generator=generator, previous=previous,
                              outputs=self.modelled, state_dim=self.task.state_dim, extra_noise=extra)

    def fit_own(self, data: TransitionDataset, generator: torch.Generator,
                start: GPHyperparameters | None = None) -> DynamicsGP:
        """θ by evidence maximisation on the target's own tuples alone, from ``start``: the judge of source samples."""
        inputs, targets = self.gp_data(data)
        return self.model.fit(inputs, targets, start=start, generator=generator, outputs=self.modelled,
                              state_dim=self.task.state_dim)

    def actor(self, policy: Policy) -> Actor:
        """u = π(φ(x)) on real observations (line 11)."""
        return policy_actor(policy, self.features, self.dtype, self.device)


def resolve_device(name: str) -> torch.device:
    """The torch device of ``cfg.device`` ("cpu", "cuda" or "cuda:N"), checked to exist on this machine."""
    try:
        device = torch.device(name)
    except RuntimeError as err:
        raise UserError(f"device={name!r} is not a torch device: choose cpu, cuda or cuda:N ({err})") from None
    if device.type == "cpu":
        return device
    if device.type != "cuda":
        raise UserError(f"device={name!r}: qtl runs on cpu or cuda (cuda:N), not {device.type}")
    if not torch.cuda.is_available():
        raise UserError(f"device={name!r}, but torch {torch.__version__} sees no CUDA GPU on this machine "
                         "(torch.cuda.is_available() is False): use device=cpu, or a CUDA build of torch")
    if device.index is not None and device.index >= torch.cuda.device_count():
        raise UserError(f"device={name!r}, but this machine has {torch.cuda.device_count()} CUDA device(s): "
                        f"use device=cpu or cuda:0 to cuda:{max(torch.cuda.device_count() - 1, 0)}")
    return device


def instantiate_checked(node: DictConfig) -> Any:  # whatever the node's `_target_` makes; Parts types it
    """Hydra's instantiate, with a component's own ValueError (a bad setting) raised as it is."""
    try:
        return instantiate(node)
    except InstantiationException as err:
        if isinstance(err.__cause__, ValueError):
            raise err.__cause__ from None
        raise


def build_search(node: DictConfig) -> PolicySearch:
    """The ``optimizer`` group's search: the class its ``_target_`` names, given the group's other keys as settings."""
    options = OmegaConf.to_container(node, resolve=True)
    search = get_class(options.pop("_target_"))
    return search(search.settings_type(**options))  # a bad setting: the settings' own ValueError


def build(cfg: DictConfig) -> Parts:
    """The parts of ``cfg``, every one checked before any work: device, task (env, spaces), components."""
    dtype = DTYPES[cfg.dtype]
    device = resolve_device(cfg.device)
    task = checked_task(OmegaConf.to_container(cfg.task, resolve=True))
    # native requested but not built, or an unknown choice: a UserError here
    engine = Engine.resolve(cfg.kernels.backend, cfg.kernels.moments)
    make_propagator = instantiate(cfg.propagation)
    check = getattr(make_propagator.func, "check_settings", None)
    if check is not None:  # e.g. an unknown propagation.sampling: a UserError here, not at the first search
        check(**make_propagator.keywords)
    check_dropout(cfg)
    make_propagator = _with_search_cost(make_propagator, task, cfg)
    make_propagator = _with_kinematics(make_propagator, task, cfg)
    make_propagator = _with_constraints(make_propagator, task)
    make_propagator = functools.partial(make_propagator, engine=engine)
    parts = Parts(
        seed=int(cfg.seed),
        dtype=dtype,
        device=device,
        task=task,
        features=AngleFeatures(task.state_dim, task.angle_dims),
        reward=ExpectedSaturatingReward.from_spec(task.reward),
        start=initial_start(task, int(cfg.seed), dtype).to(device=device),
        model=instantiate_checked(cfg.model),
        make_propagator=make_propagator,
        search=build_search(cfg.optimizer),
        make_policy=instantiate(cfg.policy),
        engine=engine,
        search_reward=search_reward_name(make_propagator),
        outputs=modelled_outputs(str(cfg.propagation.get("integration", "delta")), task.state_dim, task.kinematics),
    )
    check_lr_scales(parts.search, parts.initial_policy)
    return parts


def initial_start(task: Task, seed: int, dtype: torch.dtype) -> Gaussian:
    """N(μ_0, Σ_0) before any episode: the task's, or (estimated tasks) x_0 of the first episode with the floor as std.

    The first episode's x_0 is that of a fresh env reset with the first episode's seed.
    """
    if not task.start_estimated:
        return task.start_distribution(dtype)
    x0 = task.first_observation(derive_seed(seed, 0, ENV_STREAM))
    return diagonal_gaussian(x0, np.full_like(x0, task.start_min_std), dtype)


def _with_search_cost(make_propagator: PropagatorFactory, task: Task, cfg: DictConfig) -> PropagatorFactory:
    """Particles that score the task's declared search cost (``search_cost`` task, or auto) get it bound."""
    choice = make_propagator.keywords.get("search_cost", "widened") if hasattr(make_propagator, "keywords") else None
    if choice in (None, "widened"):
        return make_propagator
    if task.search_cost is None:
        if choice == "task":
            raise UserError(f"propagation.search_cost=task, but task {task.name} declares no search_reward: add "
                            "task.search_reward or set propagation.search_cost=widened (or auto)")
        return functools.partial(make_propagator, search_cost="widened")
    if bool(cfg.propagation.get("expected_reward", False)):
        raise UserError("propagation.search_cost scores the task's search_reward on drawn states, which has no "
                        "Gaussian expectation: set propagation.expected_reward=false or search_cost=widened")
    target, widths = task.search_cost
    cost = AngleDistanceReward(task.state_dim, task.angle_dims, target.tolist(), widths.tolist(),
                               absolute_angles=task.search_cost_angles == "absolute")
    return functools.partial(make_propagator, search_cost="task", task_search_cost=cost)


def search_reward_name(make_propagator: PropagatorFactory) -> str:
    """The reward a propagator of ``make_propagator`` has the policy search score, by name.

    ``task``: the task's own (moment matching always; particles unshaped). Else the base, ``widened``
    (``reward_width_scale``) or ``search_cost`` (the task's declared search cost), with ``+task`` where
    ``reward_task_weight`` mixes the task's own in: what the particle propagator scores
    (:func:`qtl.propagation.objective.search_reward`), by the same rule (:func:`~qtl.propagation.objective.is_shaped`).
    """
    keywords = _bound_settings(make_propagator)
    weight = keywords.get("reward_task_weight", 0.0)
    cost = keywords.get("search_cost", "widened") != "widened"
    if not is_shaped(keywords.get("reward_width_scale", 1.0), weight, cost):
        return "task"
    base = "search_cost" if cost else "widened"
    return base if weight == 0.0 else f"{base}+task"


def _bound_settings(factory: Any) -> dict[str, Any]:
    """The keywords a factory binds, through partials of partials (the outermost binding wins)."""
    inner = getattr(factory, "func", None)
    return {**(_bound_settings(inner) if inner is not None else {}), **getattr(factory, "keywords", {})}


def _with_kinematics(make_propagator: PropagatorFactory, task: Task, cfg: DictConfig) -> PropagatorFactory:
    """A propagator with speed integration gets the task's kinematics bound; a UserError where it declares none."""
    if cfg.propagation.get("integration", "delta") != "speed":
        return make_propagator
    if task.kinematics is None:
        raise UserError(f"propagation.integration=speed, but task {task.name} declares no kinematics: add "
                        "task.kinematics (positions, velocities) or set propagation.integration=delta")
    return functools.partial(make_propagator, kinematics=task.kinematics)


def _with_constraints(make_propagator: PropagatorFactory, task: Task) -> PropagatorFactory:
    """A task that declares state bounds has them bound to its propagators (``qtl.constraints``); else unchanged."""
    if not task.constraints:
        return make_propagator
    return functools.partial(make_propagator, constraints=task.constraints)


def transfer_plan(cfg: DictConfig, parts: Parts) -> TransferPlan:
    """The run's transfer plan (``cfg.transfer`` with the ``rule``): the source run loaded and checked."""
    rule = instantiate_checked(cfg.rule)
    check_transfer(cfg.transfer, rule)
    return TransferPlan(cfg.transfer, rule, parts.task, parts.features, parts.dtype, parts.device,
                        outputs=parts.modelled)
