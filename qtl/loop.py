"""Algorithm 1 of the paper, top to bottom: PILCO's learning loop, with qualitative transfer at its two seams."""

from __future__ import annotations

import contextlib
import functools
import logging
import math
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import gymnasium
import numpy as np
import torch
from omegaconf import DictConfig
from tqdm.auto import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from qtl import health
from qtl.build import Parts, build, transfer_plan
from qtl.checkpoint import prune_checkpoints, refuse_existing_run, run_checkpoint
from qtl.constraints import crossed, half_survival_step, terminating
from qtl.data import TransitionDataset
from qtl.episodes import Episode, one_step_smse, prediction_figure, random_actor, run_episode
from qtl.frames import episode_video
from qtl.gaussian import Gaussian
from qtl.hparams import outcomes, start_dashboards, write_outcomes
from qtl.kernels import Engine
from qtl.models import PreviousFit, log_evidence
from qtl.models.dynamics_gp import MIN_TRAIN_POINTS
from qtl.policy_search import SearchResult
from qtl.propagation import Propagator
from qtl.recorder import BASE_COLUMNS, THETA_P_PREFIX, RunRecorder, start_columns, start_row, theta_columns, theta_row
from qtl.run_state import RunState
from qtl.seeding import ACTION_STREAM, ENV_STREAM, JUDGE_STREAM, MODEL_STREAM, SEARCH_STREAM, seed_everything
from qtl.task import Task, diagonal_gaussian
from qtl.video import Clip

if TYPE_CHECKING:
    from matplotlib.figure import Figure

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class RunResult:
    """What a run did, per episode (the initial ones included)."""

    output_dir: Path
    returns: list[float]
    predicted_returns: list[float]  # NaN for the initial episodes
    successes: list[bool]
    health: dict[str, int] = field(default_factory=dict)  # each ``health.csv`` event, summed over the episodes

    @classmethod
    def of(cls, output_dir: Path, rows: Sequence[dict[str, Any]],
           health_rows: Sequence[dict[str, Any]] = ()) -> RunResult:
        """The result of a run's recorded rows (``metrics.csv``'s and ``health.csv``'s)."""
        totals = {event: sum(int(row.get(event, 0)) for row in health_rows) for event in health.EVENTS}
        return cls(output_dir=output_dir, returns=[float(r["return"]) for r in rows],
                   predicted_returns=[float(r["predicted_return"]) for r in rows],
                   successes=[bool(int(r["success"])) for r in rows], health=totals)


@dataclass(frozen=True)
class EpisodeResult:
    """One episode on the real system and what is recorded of it: its ``metrics.csv`` row, times, figure, video."""

    real: Episode
    row: dict[str, Any]
    fit_s: float = 0.0
    search_s: float = 0.0
    figure: Figure | None = None
    video: Clip | None = None


def run(cfg: DictConfig, output_dir: Path, *, resume: bool = False) -> RunResult:
    """Algorithm 1: learn the task of ``cfg`` in ``output_dir``, from a source run when ``cfg.transfer`` names one."""
    # -- Check everything before any work: device, task, env, spaces, components, resume point, source.
    seed_everything(cfg.seed)
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    parts = build(cfg)
    checkpoint = _resume_point(Path(output_dir), resume)
    plan = transfer_plan(cfg, parts)  # source loaded and checked
    total = cfg.random_episodes + cfg.episodes

    # -- Lines 1-2: π ← π(ψ_s) when ψ_s is transferred (else PILCO's ψ_0); θ ← θ_s waits for the first model.
    # (Resuming: the data, θ, ψ, the rule's state and the RNG streams of the last checkpoint instead.)
    state = RunState.fresh(parts, plan) if checkpoint is None else RunState.load(checkpoint, parts, plan)
    recorder = _open_recorder(cfg, output_dir, parts.task, state, total, parts.engine)
    env = parts.task.make_env()
    try:
        health.take()  # counts from here on only
        with _progress_bar(total, state.episodes, bool(cfg.progress)) as bar, health.jitter_watch():
            # -- Lines 4 and 14: repeat until the task is learned (the budget of episodes is spent).
            while state.episodes < total:
                tic = time.perf_counter()
                if state.episodes < cfg.random_episodes or len(state.data) < MIN_TRAIN_POINTS:
                    done = initial_episode(cfg, parts, state, env)  # line 3
                else:
                    done = learned_episode(cfg, parts, state, env)  # lines 12-13, 5, 6-9, 10-11
                # -- Lines 3 and 11: obtain the tuples; record the episode; checkpoint it. ---------------
                state.data.add_episode(done.real.states, done.real.actions)
                record_episode(recorder, state, done, time.perf_counter() - tic)
                state.episodes += 1
                state.save(output_dir, cfg)
                prune_checkpoints(output_dir, cfg.keep_checkpoints)
                log.info("episode %d (%s): return %.2f, predicted %.2f, success %s, fit %.1f s, policy search %.1f s",
                         done.row["episode"], done.row["kind"], done.row["return"], done.row["predicted_return"],
                         bool(done.row["success"]), done.fit_s, done.search_s)
                bar.update(1)
    finally:
        env.close()
        recorder.close()
    return RunResult.of(output_dir, state.records.rows, state.records.health)


def initial_episode(cfg: DictConfig, parts: Parts, state: RunState, env: gymnasium.Env) -> EpisodeResult:
    """Line 3: interact with the environment: π(ψ_s) if transferred (or initial_policy's), else random actions.

    Also after ``cfg.random_episodes`` while early-ended episodes have left fewer tuples than a GP needs.
    """
    if state.episodes >= cfg.random_episodes:
        log.info("only %d transitions after %d episodes (they ended early): one more initial "
                    "episode before the first model", len(state.data), state.episodes)
    if (acting := state.plan.initial_actor(state.policy)) is not None:  # ψ_s of a source (transfer.initial_policy)
        actor, kind = parts.actor(acting), "source_policy"
    else:
        actor, kind = random_actor(parts.task, np.random.default_rng(state.stream(ACTION_STREAM))), "random"
    real = run_episode(env, parts.task, actor, state.stream(ENV_STREAM))
    row = {"episode": state.episodes, "kind": kind, "predicted_return": math.nan, "predicted_survival": math.nan}
    return EpisodeResult(real, {**row, **_real_columns(parts.task, real)})


def learned_episode(cfg: DictConfig, parts: Parts, state: RunState, env: gymnasium.Env) -> EpisodeResult:
    """Lines 12-13, 5, 6-9 and 10-11: θ_p, θ and f from all tuples; ψ improved over f; π(ψ) on the real system."""
    task, plan, row = parts.task, state.plan, {"episode": state.episodes}
    # -- Line 12: learn θ_p from all tuples (evidence maximisation). -----------------------------------
    # (transfer.samples=relevance: with the source's tuples, each of noise σ_ε² / w, w its relevance.)
    tic = time.perf_counter()
    # (Their relevance is judged by θ of the target's tuples alone, fitted here too.)
    samples = plan.source_samples(functools.partial(parts.fit_own, state.data, state.generator(JUDGE_STREAM)))
    model = parts.fit_dynamics(state.data, state.generator(MODEL_STREAM), start=plan.fit_start(),
                               previous=state.previous, samples=samples)
    state.previous = PreviousFit.of(model)
    theta_p = model.hyperparameters
    compliance = plan.compliance(model if samples is None else model.head(len(state.data)))  # Eq. 14 (NaN: no source)
    # -- Lines 2, 13 and 5: θ_0 = θ_s, then the updating rule; f inferred with θ. ------------------------
    # (Λ below transfer.min_compliance here at the first model: θ = θ_p and ψ = PILCO's ψ_0.)
    state.theta = plan.update(theta_p, len(state.data), compliance, state.policy, model.outputs)
    if state.theta is not theta_p:
        model.hyperparameters = state.theta
    fit_s = time.perf_counter() - tic

    # -- Lines 6-9: evaluate π over f (V^π, Eq. 4) and improve ψ until convergence. -----------------------
    tic = time.perf_counter()
    start = parts.start
    if task.start_estimated:  # no start distribution given: μ_0, Σ_0 from the x_0 seen so far
        mean, std = estimated_start(task, state.data)
        start = diagonal_gaussian(mean, std, parts.dtype).to(device=parts.device)
        row.update(start_row(mean, std))
    propagator = parts.make_propagator(model, state.policy, parts.reward, angle_dims=task.angle_dims)
    with tqdm(desc=f"policy search {state.episodes}", unit="eval", leave=False, disable=not cfg.progress) as evals:
        found = parts.search(state.policy, functools.partial(propagator.expected_return, start, task.horizon),
                             generator=state.generator(SEARCH_STREAM), tick=functools.partial(evals.update, 1))
    search_s = time.perf_counter() - tic
    predicted = predicted_return(propagator, found, parts.search_reward, start, task.horizon)
    row.update(predicted_survival(propagator, task, start))  # S_H and where S_t < 0.5 (task.constraints)

    # -- Lines 10-11: apply π(ψ) on the real system to obtain more tuples. -----------------------------
    seed = state.stream(ENV_STREAM)
    real = run_episode(env, task, parts.actor(state.policy), seed)
    row.update(kind="policy", predicted_return=predicted, model_smse=one_step_smse(model, real, parts.features,
               parts.dtype), model_log_evidence=log_evidence(model), policy_evaluations=found.evaluations,
               compliance=compliance, fallback=int(plan.fallen_back), **theta_row(state.theta, outputs=model.outputs),
               **theta_row(theta_p, THETA_P_PREFIX, model.outputs), **plan.compliance_row(), **plan.sample_row())
    figure = video = None
    if cfg.figure_every > 0 and (state.episodes - cfg.random_episodes) % cfg.figure_every == 0:
        figure = prediction_figure(propagator, start, task.horizon, real, f"episode {state.episodes}: predicted vs "
                                   "real", task.state_names, task.constraints)
        video = episode_video(task, real, seed) if cfg.get("video", True) else None  # the same episode, rendered
    return EpisodeResult(real, {**row, **_real_columns(task, real)}, fit_s, search_s, figure, video)


def record_episode(recorder: RunRecorder, state: RunState, done: EpisodeResult, episode_s: float) -> None:
    """Record the episode ``state`` is at: its row, times and health counts, and the run's outcomes so far."""
    episode = state.episodes
    recorder.record(done.row, {"model_fit_s": done.fit_s, "policy_search_s": done.search_s, "episode_s": episode_s},
                    done.figure, {"resumed": int(episode == state.resumed_at), **health.take()}, done.video)
    write_outcomes(recorder.writer, outcomes(state.records.rows, state.records.timings), episode)


def _real_columns(task: Task, real: Episode) -> dict[str, Any]:
    """The ``metrics.csv`` columns of what an episode did on the real system: returns, success, length, distance."""
    return {"return": float(real.rewards.sum()), "env_return": float(real.env_rewards.sum()),
            "success": int(task.succeeded(real.states)), "length": len(real.rewards),
            "final_distance": float(task.distance(real.states[-1:])[0]),
            "crossed": int(crossed(task.constraints, real.states))}


def _open_recorder(cfg: DictConfig, output_dir: Path, task: Task, state: RunState, total: int,
                   engine: Engine) -> RunRecorder:
    """The run's recorder over ``state``'s records (a fresh run's dashboards written); plan, kernels, resume logged."""
    if state.resumed_at is not None and state.episodes >= total:  # e.g. a sweep resuming all its runs: one line
        log.info("%s finished already (it holds %d episodes, the budget is %d): nothing to run",
                 output_dir, state.episodes, total)
    elif state.resumed_at is not None:
        log.info("resuming %s after episode %d", output_dir, state.episodes - 1)
    modelled = state.plan.outputs  # θ's columns name the state dimensions the GP models
    columns = (BASE_COLUMNS + theta_columns(len(modelled), task.gp_input_dim, outputs=modelled)
               + theta_columns(len(modelled), task.gp_input_dim, THETA_P_PREFIX, modelled)
               + (start_columns(task.state_dim) if task.start_estimated else []) + state.plan.compliance_columns()
               + state.plan.sample_columns())
    if state.episodes < total:
        log.info("%s", state.plan.describe())
        log.info("kernels: %s; exp sums %s, moments %s", engine.describe(), engine.exp_sums, engine.moments)
    recorder = RunRecorder(output_dir, columns, state.records)
    if not state.records.rows:  # HParams session, chart layout, config and plan: once per run, not again on resume
        start_dashboards(recorder.writer, cfg, task, state.plan)
    return recorder


def estimated_start(task: Task, data: TransitionDataset) -> tuple[np.ndarray, np.ndarray]:
    """μ_0 `D`, σ_0 `D` fitted to the initial states of ``data``'s episodes (:meth:`Task.estimate_start`); logged."""
    initial = np.stack([data.episode(i)[0][0] for i in range(data.num_episodes)])  # N x D
    mean, std = task.estimate_start(initial)
    log.info("start distribution estimated from %d initial state(s): mean %s, std %s", len(initial),
             np.array2string(mean, precision=4), np.array2string(std, precision=4))
    return mean, std


def predicted_return(
    propagator: Propagator, found: SearchResult, search_reward: str, start: Gaussian, horizon: int
) -> float:
    """V^π of the found ψ under the task's reward (Eq. 4): the search's value, or a rollout if it searched another.

    ``search_reward`` names what the search scored (:func:`qtl.build.search_reward_name`): other than ``task``
    (e.g. ``propagation.reward_width_scale``'s wider reward), the recorded prediction is one more rollout, scored
    by the task's reward.
    """
    if search_reward == "task":
        return found.value
    with torch.no_grad():
        return float(propagator.rollout(start, horizon).value)


def predicted_survival(propagator: Propagator, task: Task, start: Gaussian) -> dict[str, float]:
    """S_H of the found ψ's prediction and the first step t with S_t < 0.5 (NaN: never), as ``metrics.csv`` columns.

    One more rollout, without gradients, where the task declares terminate constraints (``qtl.constraints``);
    none: S_H = 1 and no rollout.
    """
    if not terminating(task.constraints):
        return {"predicted_survival": 1.0, "survival_half_step": math.nan}
    with torch.no_grad():
        survival = propagator.rollout(start, task.horizon).survival
    half = half_survival_step(survival)
    return {"predicted_survival": float(survival[-1]), "survival_half_step": math.nan if half is None else half}


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
