"""Algorithm 1 of the paper, top to bottom: PILCO's learning loop, with qualitative transfer at its two seams."""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from tqdm.auto import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from qtl.checkpoint import (
    CHECKPOINT_DIR,
    latest_checkpoint,
    load_checkpoint,
    save_checkpoint,
    set_rng_state,
)
from qtl.data import TransitionDataset, gp_training_pairs
from qtl.errors import CheckpointError, NonFiniteObjective
from qtl.features import AngleFeatures
from qtl.models import DynamicsGP, GPHyperparameters, SparseDynamicsGP
from qtl.policies import Policy, SquashedPolicy
from qtl.recorder import BASE_COLUMNS, RunRecorder, theta_columns, theta_row, trajectory_figure
from qtl.rewards import ExpectedSaturatingReward
from qtl.seeding import seed_everything
from qtl.task import Task
from qtl.transfer.plan import TransferPlan

log = logging.getLogger(__name__)

DTYPES = {"float64": torch.float64, "float32": torch.float32}
# Independent random streams, each derived from (seed, episode, stream): a resumed run draws
# exactly what an uninterrupted one would.
ENV_STREAM, ACTION_STREAM, MODEL_STREAM, SEARCH_STREAM, POLICY_INIT_STREAM = range(5)
# Draws from the start distribution from which the initial support points are taken.
START_DRAWS = 1000


@dataclass(frozen=True)
class RunResult:
    """What a run did, per episode (the random ones included)."""

    output_dir: Path
    returns: list[float]
    predicted_returns: list[float]  # NaN for random episodes
    successes: list[bool]

    @property
    def first_success(self) -> int | None:
        """Index of the first successful episode, or None."""
        return next((i for i, s in enumerate(self.successes) if s), None)


@dataclass(frozen=True)
class Episode:
    """One episode on the real system: states `T+1 x D`, actions `T x F`, rewards `T`."""

    states: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray


def derive_seed(seed: int, episode: int, stream: int) -> int:
    """A 32-bit seed for one random stream of one episode."""
    return int(np.random.SeedSequence([seed, episode, stream]).generate_state(1)[0])


def torch_generator(seed: int, episode: int, stream: int) -> torch.Generator:
    """A torch Generator seeded for one random stream of one episode."""
    return torch.Generator().manual_seed(derive_seed(seed, episode, stream))


def instantiate_checked(node: DictConfig) -> Any:
    """Hydra's instantiate, with a component's own ValueError (a bad setting) raised as it is."""
    try:
        return instantiate(node)
    except InstantiationException as err:
        if isinstance(err.__cause__, ValueError):
            raise err.__cause__ from None
        raise


def run_episode(env: gymnasium.Env, task: Task, act: Callable[[np.ndarray], np.ndarray], seed: int) -> Episode:
    """Apply ``act`` on the real system for at most H steps (Algorithm 1, lines 3 and 11).

    Rewards are the task's saturating reward of each successor state: the env's own when it
    exposes the same ``reward_spec``, else the configured ``task.reward`` of the observation.
    """
    obs, _ = env.reset(seed=seed)
    states, actions, rewards = [obs], [], []
    for _ in range(task.horizon):
        action = np.clip(act(obs), -task.action_bound, task.action_bound)
        obs, reward, terminated, truncated, _ = env.step(action.astype(env.action_space.dtype))
        states.append(obs)
        actions.append(action)
        rewards.append(reward if task.reward_from_env else task.reward(obs))
        if terminated or truncated:
            break
    return Episode(np.asarray(states, dtype=float), np.asarray(actions, dtype=float), np.asarray(rewards, dtype=float))


def random_actor(task: Task, rng: np.random.Generator) -> Callable[[np.ndarray], np.ndarray]:
    """Actions uniform in the action bounds, whatever the state (Algorithm 1, line 3)."""
    return lambda _obs: rng.uniform(-task.action_bound, task.action_bound)


def resolve_device(name: str) -> torch.device:
    """The torch device of ``cfg.device`` ("cpu", "cuda" or "cuda:N"), checked to exist on this machine."""
    try:
        device = torch.device(name)
    except RuntimeError as err:
        raise ValueError(f"device={name!r} is not a torch device: choose cpu, cuda or cuda:N ({err})") from None
    if device.type == "cpu":
        return device
    if device.type != "cuda":
        raise ValueError(f"device={name!r}: qtl runs on cpu or cuda (cuda:N), not {device.type}")
    if not torch.cuda.is_available():
        raise ValueError(f"device={name!r}, but torch {torch.__version__} sees no CUDA GPU on this machine "
                         "(torch.cuda.is_available() is False): use device=cpu, or a CUDA build of torch")
    if device.index is not None and device.index >= torch.cuda.device_count():
        raise ValueError(f"device={name!r}, but this machine has {torch.cuda.device_count()} CUDA device(s)")
    return device


def policy_actor(
    policy: Policy, features: AngleFeatures, dtype: torch.dtype, device: torch.device | str = "cpu"
) -> Callable[[np.ndarray], np.ndarray]:
    """u = π(φ(x)) on a real observation (Algorithm 1, line 11); the action back on the CPU as numpy."""

    def act(obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return policy(features(torch.as_tensor(obs, dtype=dtype, device=device))).cpu().numpy()

    return act


def fit_dynamics(
    data: TransitionDataset,
    features: AngleFeatures,
    cfg: DictConfig,
    generator: torch.Generator,
    dtype: torch.dtype,
    start: GPHyperparameters | None = None,
    device: torch.device | str = "cpu",
) -> DynamicsGP:
    """Learn θ_p by evidence maximisation on all tuples (line 12), from ``start`` or PILCO's heuristic.

    Above ``cfg.sparse_above`` tuples the model is the sparse GP with ``cfg.inducing`` inducing inputs.
    The model lives on ``device`` (that of its training tuples).
    """
    inputs, targets = gp_training_pairs(data, features, dtype, device)
    if cfg.get("sparse_above") is not None and len(inputs) > cfg.sparse_above:
        log.info("%d tuples > model.sparse_above=%d: the sparse GP, %d inducing inputs", len(inputs),
                 cfg.sparse_above, min(cfg.inducing, len(inputs)))
        model = SparseDynamicsGP(inputs, targets, hyperparameters=start, num_inducing=cfg.inducing,
                                 generator=generator, dtype=dtype)
    else:
        model = DynamicsGP(inputs, targets, hyperparameters=start, dtype=dtype)
    model.fit(restarts=cfg.restarts, max_iter=cfg.max_iter, generator=generator)
    return model


def initial_policy(cfg: DictConfig, task: Task, features: AngleFeatures, dtype: torch.dtype) -> Policy:
    """π(ψ_0) as PILCO starts it: the configured policy around the start state, squashed (line 1)."""
    generator = torch_generator(cfg.seed, 0, POLICY_INIT_STREAM)
    draws = task.start_distribution(dtype).sample(START_DRAWS, generator=generator)  # START_DRAWS x D
    make = instantiate(cfg.policy)
    inner = make(task.feature_dim, task.action_dim, start_features=features(draws), generator=generator, dtype=dtype)
    return SquashedPolicy(inner, torch.as_tensor(task.action_bound, dtype=dtype))


def one_step_smse(model: DynamicsGP, episode: Episode, features: AngleFeatures, dtype: torch.dtype) -> float:
    """Model fit quality: one-step prediction error on an episode it has not seen, over target variance."""
    data = TransitionDataset(episode.states.shape[1], episode.actions.shape[1])
    data.add_episode(episode.states, episode.actions)
    inputs, targets = gp_training_pairs(data, features, dtype, model.train_x.device)
    mean, _ = model.predict(inputs)
    mse = ((mean - targets) ** 2).mean(0)
    return float((mse / model.train_y.var(0)).mean())


@contextlib.contextmanager
def progress_bar(total: int, initial: int, enabled: bool) -> Iterator[tqdm]:
    """A progress bar over episodes, log lines routed around it; silent when disabled."""
    with logging_redirect_tqdm(), tqdm(total=total, initial=initial, disable=not enabled, unit="episode") as bar:
        yield bar


def run(cfg: DictConfig, output_dir: Path, *, resume: bool = False) -> RunResult:
    """Algorithm 1: learn the task of ``cfg`` in ``output_dir``, from a source run when ``cfg.transfer`` names one."""
    # -- Check everything before any work: task, env, spaces, resume point. -----------------------
    dtype = DTYPES[cfg.dtype]
    device = resolve_device(cfg.device)
    task = Task.from_config(OmegaConf.to_container(cfg.task, resolve=True))
    if resume:
        checkpoint = load_checkpoint(latest_checkpoint(output_dir))
    elif any((Path(output_dir) / CHECKPOINT_DIR).glob("episode_*.pt")):
        raise CheckpointError(
            f"{str(output_dir)!r} already holds a run's checkpoints: resume={output_dir} continues it (resume=auto in "
            "a sweep), or choose another hydra.run.dir; nothing was overwritten"
        )
    else:
        checkpoint = None
    seed_everything(cfg.seed)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    features = AngleFeatures(task.state_dim, task.angle_dims)
    reward = ExpectedSaturatingReward.from_spec(task.reward)
    start = task.start_distribution(dtype).to(device=device)
    make_propagator = instantiate(cfg.propagation)
    search = instantiate_checked(cfg.optimizer)
    plan = TransferPlan(cfg.transfer, instantiate_checked(cfg.rule), task, features, dtype,
                        device)  # source loaded and checked
    total = cfg.random_episodes + cfg.episodes

    # -- Lines 1-2: π ← π(ψ_s) when ψ_s is transferred (else PILCO's ψ_0); θ_s waits for the first model.
    policy = initial_policy(cfg, task, features, dtype).to(device)
    plan.initial_policy(policy)
    data = TransitionDataset(task.state_dim, task.action_dim)
    rows: list[dict[str, Any]] = []
    timings: list[dict[str, Any]] = []
    theta: GPHyperparameters | None = None  # θ of the latest model (none before the first fit)
    first = 0
    if checkpoint is not None:
        data = TransitionDataset.from_state(checkpoint["dataset"])
        policy.load_state_dict(checkpoint["policy"])
        rows, timings = list(checkpoint["metrics"]), list(checkpoint["timings"])
        theta = None if checkpoint["theta"] is None else GPHyperparameters(**checkpoint["theta"])
        if "transfer" in checkpoint:  # checkpoints of runs made before transfer existed are PILCO runs
            plan.load_state_dict(checkpoint["transfer"])
        first = checkpoint["episode"] + 1
        set_rng_state(checkpoint["rng"])
        log.info("resuming %s after episode %d", output_dir, checkpoint["episode"])
    columns = (BASE_COLUMNS + theta_columns(task.state_dim, task.gp_input_dim)
               + theta_columns(task.state_dim, task.gp_input_dim, "theta_p"))
    log.info("%s", plan.describe())
    recorder = RunRecorder(output_dir, columns, rows, timings)
    env = task.make_env()
    show_progress = bool(cfg.progress)

    try:
        with progress_bar(total, first, show_progress) as bar:
            for episode in range(first, total):
                row: dict[str, Any] = {"episode": episode}
                figure = None
                if episode < cfg.random_episodes:
                    # -- Line 3: interact with the environment: π(ψ_s) if transferred, else random actions.
                    if plan.transfer_policy:
                        actor, kind = policy_actor(policy, features, dtype, device), "source_policy"
                    else:
                        rng = np.random.default_rng(derive_seed(cfg.seed, episode, ACTION_STREAM))
                        actor, kind = random_actor(task, rng), "random"
                    real = run_episode(env, task, actor, derive_seed(cfg.seed, episode, ENV_STREAM))
                    row.update(kind=kind, predicted_return=math.nan)
                    fit_s = search_s = 0.0
                else:
                    # -- Line 12: learn θ_p from all tuples (evidence maximisation). ---------------
                    tic = time.perf_counter()
                    model = fit_dynamics(data, features, cfg.model, torch_generator(cfg.seed, episode, MODEL_STREAM),
                                         dtype, start=plan.fit_start(), device=device)
                    theta_p = model.hyperparameters
                    compliance = plan.compliance(model)  # Eq. 14 (NaN without a source)
                    # -- Lines 2, 13 and 5: θ_0 = θ_s, then the updating rule; f inferred with θ. --
                    theta = plan.update(theta_p, len(data), compliance)
                    if theta is not theta_p:
                        model.hyperparameters = theta
                    fit_s = time.perf_counter() - tic

                    # -- Lines 6-9: evaluate π over f (V^π, Eq. 4) and improve ψ until convergence.
                    tic = time.perf_counter()
                    propagator = make_propagator(model, policy, reward, angle_dims=task.angle_dims)
                    with tqdm(desc=f"policy search {episode}", unit="eval", leave=False,
                              disable=not show_progress) as evals:
                        found = search(policy, functools.partial(propagator.expected_return, start, task.horizon),
                                       generator=torch_generator(cfg.seed, episode, SEARCH_STREAM),
                                       tick=functools.partial(evals.update, 1))
                    search_s = time.perf_counter() - tic

                    # -- Lines 10-11: apply π(ψ) on the real system to obtain more tuples. ---------
                    actor = policy_actor(policy, features, dtype, device)
                    real = run_episode(env, task, actor, derive_seed(cfg.seed, episode, ENV_STREAM))
                    row.update(
                        kind="policy",
                        predicted_return=found.value,
                        model_smse=one_step_smse(model, real, features, dtype),
                        model_log_evidence=_log_evidence(model),
                        policy_evaluations=found.evaluations,
                        compliance=compliance,
                        fallback=int(plan.fallen_back),
                        **theta_row(theta),
                        **theta_row(theta_p, "theta_p"),
                    )
                    learned = episode - cfg.random_episodes
                    if cfg.figure_every > 0 and learned % cfg.figure_every == 0:
                        figure = _prediction_figure(propagator, start, task, real, episode)

                # -- Append the tuples; record the episode; checkpoint it. ------------------------
                data.add_episode(real.states, real.actions)
                row.update(
                    {"return": float(real.rewards.sum())},
                    success=int(task.succeeded(real.states)),
                    length=len(real.rewards),
                    final_distance=float(task.distance(real.states[-1:])[0]),
                )
                recorder.record(row, {"model_fit_s": fit_s, "policy_search_s": search_s}, figure)
                save_checkpoint(output_dir, episode, {
                    "config": OmegaConf.to_yaml(cfg),
                    "dataset": data.state(),
                    "theta": None if theta is None else theta.state_dict(),
                    "transfer": plan.state_dict(),
                    "policy": {k: v.detach().cpu().clone() for k, v in policy.state_dict().items()},
                    "metrics": recorder.rows,
                    "timings": recorder.timings,
                })
                log.info(
                    "episode %d (%s): return %.2f, predicted %.2f, success %s, fit %.1f s, policy search %.1f s",
                    episode, row["kind"], row["return"], row["predicted_return"], bool(row["success"]), fit_s,
                    search_s,
                )
                bar.update(1)
    finally:
        env.close()
        recorder.close()

    return RunResult(
        output_dir=output_dir,
        returns=[float(r["return"]) for r in recorder.rows],
        predicted_returns=[float(r["predicted_return"]) for r in recorder.rows],
        successes=[bool(int(r["success"])) for r in recorder.rows],
    )


def _log_evidence(model: DynamicsGP) -> float:
    """Mean over outputs of the log evidence per data point (with priors) of the fitted model."""
    model.train()
    with torch.no_grad():
        value = float(model.log_evidence().mean())
    model.eval()
    return value


def _prediction_figure(propagator: Any, start: Any, task: Task, real: Episode, episode: int) -> Any:
    """Predicted state distribution of the final policy against what the real system did."""
    try:
        with torch.no_grad():
            predicted = propagator.rollout(start, task.horizon).states  # (H+1) x D
    except (NonFiniteObjective, torch.linalg.LinAlgError) as err:
        log.warning("no prediction figure for episode %d: the predicted rollout broke down (%s)", episode, err)
        return None
    mean = predicted.mean.cpu().numpy()
    std = torch.diagonal(predicted.cov, dim1=-2, dim2=-1).clamp_min(0).sqrt().cpu().numpy()
    return trajectory_figure(mean, std, real.states, f"episode {episode}: predicted vs real")

