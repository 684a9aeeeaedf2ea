"""Algorithm 1 of the paper, top to bottom: PILCO's learning loop, with qualitative transfer at its two seams."""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm.auto import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from qtl import health
from qtl.build import build, transfer_plan
from qtl.checkpoint import (
    prune_checkpoints,
    refuse_existing_run,
    run_checkpoint,
    save_checkpoint,
    set_rng_state,
)
from qtl.data import TransitionDataset
from qtl.episodes import one_step_smse, prediction_figure, random_actor, run_episode
from qtl.gaussian import Gaussian
from qtl.hparams import outcomes, start_dashboards, write_outcomes
from qtl.models import GPHyperparameters, PreviousFit, log_evidence
from qtl.models.dynamics_gp import MIN_TRAIN_POINTS
from qtl.policy_search import SearchResult
from qtl.propagation import Propagator
from qtl.recorder import (
    BASE_COLUMNS,
    THETA_P_PREFIX,
    RunRecorder,
    start_columns,
    start_row,
    theta_columns,
    theta_row,
)
from qtl.rewards import ExpectedSaturatingReward
from qtl.seeding import (
    ACTION_STREAM,
    ENV_STREAM,
    MODEL_STREAM,
    SEARCH_STREAM,
    derive_seed,
    seed_everything,
    torch_generator,
)
from qtl.task import Task, diagonal_gaussian

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunResult:
    """What a run did, per episode (the initial ones included)."""

    output_dir: Path
    returns: list[float]
    predicted_returns: list[float]  # NaN for the initial episodes
    successes: list[bool]


def run(cfg: DictConfig, output_dir: Path, *, resume: bool = False) -> RunResult:
    """Algorithm 1: learn the task of ``cfg`` in ``output_dir``, from a source run when ``cfg.transfer`` names one."""
    # -- Check everything before any work: device, task, env, spaces, components, resume point, source.
    seed_everything(cfg.seed)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    parts = build(cfg)
    task, features, start = parts.task, parts.features, parts.start
    checkpoint = _resume_point(Path(output_dir), resume)
    plan = transfer_plan(cfg, parts)  # source loaded and checked
    total = cfg.random_episodes + cfg.episodes

    # -- Lines 1-2: π ← π(ψ_s) when ψ_s is transferred (else PILCO's ψ_0); θ_s waits for the first model.
    policy = parts.initial_policy()
    plan.initial_policy(policy)
    data = TransitionDataset(task.state_dim, task.action_dim, task.angle_dims)
    rows: list[dict[str, Any]] = []
    timings: list[dict[str, Any]] = []
    health_rows: list[dict[str, Any]] = []
    theta: GPHyperparameters | None = None  # θ of the latest model (none before the first fit)
    previous: PreviousFit | None = None  # θ_p (and Z) of the latest fit, where model.warm_start starts from
    first = 0
    if checkpoint is not None:
        data = TransitionDataset.from_state(checkpoint["dataset"], task.angle_dims)
        policy.load_state_dict(checkpoint["policy"])
        rows, timings = list(checkpoint["metrics"]), list(checkpoint["timings"])
        health_rows = list(checkpoint.get("health", []))  # absent in checkpoints made before health.csv
        theta = None if checkpoint["theta"] is None else GPHyperparameters(**checkpoint["theta"])
        previous = PreviousFit.of_checkpoint(checkpoint)
        if "transfer" in checkpoint:  # checkpoints of runs made before transfer existed are PILCO runs
            plan.load_state_dict(checkpoint["transfer"])
        first = checkpoint["episode"] + 1
        set_rng_state(checkpoint["rng"])
        if first >= total:  # e.g. a sweep resuming all its runs: one line, not the resume and transfer lines
            log.info("%s finished already (it holds %d episodes, the budget is %d): nothing to run",
                     output_dir, first, total)
        else:
            log.info("resuming %s after episode %d", output_dir, checkpoint["episode"])
    columns = (BASE_COLUMNS + theta_columns(task.state_dim, task.gp_input_dim)
               + theta_columns(task.state_dim, task.gp_input_dim, THETA_P_PREFIX)
               + (start_columns(task.state_dim) if task.start_estimated else []))
    if first < total:
        log.info("%s", plan.describe())
    recorder = RunRecorder(output_dir, columns, rows, timings, health_rows)
    if not rows:  # HParams session, chart layout, config and plan: once per run, not again on resume
        start_dashboards(recorder.writer, cfg, task, plan)
    env = task.make_env()
    show_progress = bool(cfg.progress)

    try:
        health.take()  # counts from here on only
        with _progress_bar(total, first, show_progress) as bar, health.jitter_watch():
            for episode in range(first, total):
                row: dict[str, Any] = {"episode": episode}
                episode_tic = time.perf_counter()
                figure = None
                if episode < cfg.random_episodes or len(data) < MIN_TRAIN_POINTS:
                    # -- Line 3: interact with the environment: π(ψ_s) if transferred, else random actions
                    # (again while early-ended episodes have left fewer tuples than a GP needs).
                    if episode >= cfg.random_episodes:
                        log.warning("only %d transitions after %d episodes (they ended early): one more initial "
                                    "episode before the first model", len(data), episode)
                    if plan.transfer_policy:
                        actor, kind = parts.actor(policy), "source_policy"
                    else:
                        rng = np.random.default_rng(derive_seed(cfg.seed, episode, ACTION_STREAM))
                        actor, kind = random_actor(task, rng), "random"
                    real = run_episode(env, task, actor, derive_seed(cfg.seed, episode, ENV_STREAM))
                    row.update(kind=kind, predicted_return=math.nan)
                    fit_s = search_s = 0.0
                else:
                    # -- Line 12: learn θ_p from all tuples (evidence maximisation). ---------------
                    tic = time.perf_counter()
                    model = parts.fit_dynamics(data, torch_generator(cfg.seed, episode, MODEL_STREAM),
                                               start=plan.fit_start(), previous=previous)
                    previous = PreviousFit.of(model)
                    theta_p = model.hyperparameters
                    compliance = plan.compliance(model)  # Eq. 14 (NaN without a source)
                    # -- Lines 2, 13 and 5: θ_0 = θ_s, then the updating rule; f inferred with θ. --
                    # (Λ below transfer.min_compliance here at the first model: θ = θ_p and ψ = PILCO's ψ_0.)
                    theta = plan.update(theta_p, len(data), compliance, policy)
                    if theta is not theta_p:
                        model.hyperparameters = theta
                    fit_s = time.perf_counter() - tic

                    # -- Lines 6-9: evaluate π over f (V^π, Eq. 4) and improve ψ until convergence.
                    tic = time.perf_counter()
                    if task.start_estimated:  # no start distribution given: μ_0, Σ_0 from the x_0 seen so far
                        mean, std = estimated_start(task, data)
                        start = diagonal_gaussian(mean, std, parts.dtype).to(device=parts.device)
                        row.update(start_row(mean, std))
                    propagator = parts.make_propagator(model, policy, parts.reward, angle_dims=task.angle_dims)
                    with tqdm(desc=f"policy search {episode}", unit="eval", leave=False,
                              disable=not show_progress) as evals:
                        found = parts.search(policy, functools.partial(propagator.expected_return, start, task.horizon),
                                             generator=torch_generator(cfg.seed, episode, SEARCH_STREAM),
                                             tick=functools.partial(evals.update, 1))
                    search_s = time.perf_counter() - tic
                    predicted = predicted_return(propagator, found, parts.reward, start, task.horizon)

                    # -- Lines 10-11: apply π(ψ) on the real system to obtain more tuples. ---------
                    real = run_episode(env, task, parts.actor(policy), derive_seed(cfg.seed, episode, ENV_STREAM))
                    row.update(
                        kind="policy",
                        predicted_return=predicted,
                        model_smse=one_step_smse(model, real, features, parts.dtype),
                        model_log_evidence=log_evidence(model),
                        policy_evaluations=found.evaluations,
                        compliance=compliance,
                        fallback=int(plan.fallen_back),
                        **theta_row(theta),
                        **theta_row(theta_p, THETA_P_PREFIX),
                    )
                    learned = episode - cfg.random_episodes
                    if cfg.figure_every > 0 and learned % cfg.figure_every == 0:
                        figure = prediction_figure(propagator, start, task.horizon, real,
                                                   f"episode {episode}: predicted vs real", task.state_names)

                # -- Append the tuples; record the episode; checkpoint it. ------------------------
                data.add_episode(real.states, real.actions)
                row.update(
                    {"return": float(real.rewards.sum()), "env_return": float(real.env_rewards.sum())},
                    success=int(task.succeeded(real.states)),
                    length=len(real.rewards),
                    final_distance=float(task.distance(real.states[-1:])[0]),
                )
                recorder.record(row, {"model_fit_s": fit_s, "policy_search_s": search_s,
                                      "episode_s": time.perf_counter() - episode_tic}, figure,
                                {"resumed": int(checkpoint is not None and episode == first), **health.take()})
                write_outcomes(recorder.writer, outcomes(recorder.rows, recorder.timings), episode)
                save_checkpoint(output_dir, episode, {
                    "config": OmegaConf.to_yaml(cfg),
                    "dataset": data.state(),
                    "theta": None if theta is None else theta.state_dict(),
                    "previous_fit": None if previous is None else previous.state_dict(),
                    "transfer": plan.state_dict(),
                    "policy": {k: v.detach().cpu().clone() for k, v in policy.state_dict().items()},
                    "metrics": recorder.rows,
                    "timings": recorder.timings,
                    "health": recorder.health,
                })
                prune_checkpoints(output_dir, cfg.keep_checkpoints)
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


def estimated_start(task: Task, data: TransitionDataset) -> tuple[np.ndarray, np.ndarray]:
    """μ_0 `D`, σ_0 `D` fitted to the initial states of ``data``'s episodes (:meth:`Task.estimate_start`); logged."""
    initial = np.stack([data.episode(i)[0][0] for i in range(data.num_episodes)])  # N x D
    mean, std = task.estimate_start(initial)
    log.info("start distribution estimated from %d initial state(s): mean %s, std %s", len(initial),
             np.array2string(mean, precision=4), np.array2string(std, precision=4))
    return mean, std


def predicted_return(
    propagator: Propagator, found: SearchResult, reward: ExpectedSaturatingReward, start: Gaussian, horizon: int
) -> float:
    """V^π of the found ψ under the task's ``reward`` (Eq. 4): the search's value, or a rollout if it searched another.

    A propagator whose ``search_reward`` is not the task's (``propagation.reward_width_scale``) valued ψ
    under that wider reward; the recorded prediction is then one more rollout, scored by the task's reward.
    """
    if getattr(propagator, "search_reward", reward) is reward:
        return found.value
    with torch.no_grad():
        return float(propagator.rollout(start, horizon).value)


def _resume_point(output_dir: Path, resume: bool) -> dict[str, Any] | None:
    """The last checkpoint to continue from, or None for a fresh run (refused where a run already lies)."""
    if resume:
        return run_checkpoint(output_dir)
    refuse_existing_run(output_dir)
    return None


@contextlib.contextmanager
def _progress_bar(total: int, initial: int, enabled: bool) -> Iterator[tqdm]:
    """A progress bar over episodes, log lines routed around it; silent when disabled."""
    with logging_redirect_tqdm(), tqdm(total=total, initial=initial, disable=not enabled, unit="episode") as bar:
        yield bar
