"""The policy-search benchmarks' shared case: cart-pole data, the loop's search settings, a timed evaluation.

Data: real transitions of the configured task (by default the 0.5 kg cart-pole of ``configs/task/cartpole.yaml``),
episodes of uniform random actions alternating with episodes of a random RBF policy, cut at n tuples, seeded.
One exact ``DynamicsGP`` per n is fitted once in float64 and cached (:func:`ensure_model`). An evaluation is one
rollout + gradient (:func:`rollout_and_gradient`), a search round the rollout + gradient of the search's R
starting points at once (:func:`batched_round`).
"""

from __future__ import annotations

import hashlib
import json
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra import compose, initialize_config_module
from omegaconf import DictConfig, OmegaConf

from qtl.bench.record import ROOT
from qtl.build import Parts, build
from qtl.config import register_configs
from qtl.data import TransitionDataset, gp_training_pairs
from qtl.episodes import policy_actor, random_actor, run_episode
from qtl.features import AngleFeatures
from qtl.gaussian import Gaussian
from qtl.models import DynamicsGP
from qtl.policies import RBFPolicy, SquashedPolicy, batched_policy, psi_names, set_psi, stack_psi
from qtl.propagation import Propagator
from qtl.seeding import ENV_STREAM, SEARCH_STREAM, derive_seed, torch_generator
from qtl.task import Task

# The loop's settings per propagator: Hydra overrides of the default `train` config.
# The particle rows' shared settings: the mc_pilco recipe's propagation (fresh noise every evaluation, the reward
# of the drawn states), so that pathwise against marginal compares like with like.
PARTICLE_SEARCH = ["propagation=particles", "propagation.resample_every=1", "propagation.expected_reward=false",
                   "optimizer=adam", "optimizer.steps=500"]
PROPAGATORS: dict[str, list[str]] = {
    "moment_matching": ["propagation=moment_matching", "optimizer=lbfgs"],
    "particles": PARTICLE_SEARCH,
    # Pathwise GP samples (issue 19), with the random features and the float32 path values of the mc_pilco
    # recipe (those two act on pathwise sampling only); otherwise the row above, whose sampling is marginal.
    "particles_pathwise": [*PARTICLE_SEARCH, "propagation.sampling=pathwise", "propagation.num_features=256",
                           "propagation.path_dtype=float32"],
}
# Data collection: random-action episodes alternate with episodes of a random RBF policy whose
# targets (before squashing) are drawn with this std, so that the data cover swings, not only rest.
RANDOM_POLICY_TARGET_STD = 1.0
DATA_POLICY_STREAM = 7  # random stream of the data-collecting RBF policies (not one of the loop's)
SEARCH_EPISODE = 1  # the search's generator is the one the loop's first learned episode gets
MODEL_FIT_RESTARTS = 1
DATA_VERSION = 1  # bump when the data or the fit change, to invalidate cached models
CACHE_DIR = ROOT / "runs" / "bench_policy_search"


def compose_config(propagator: str, dtype_name: str, overrides: list[str]) -> DictConfig:
    """The default ``train`` config with the propagator's settings, the dtype and ``overrides``."""
    register_configs()
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        return compose(config_name="train", overrides=[*PROPAGATORS[propagator], f"dtype={dtype_name}", *overrides])


def data_policy(task: Task, num_basis: int, generator: torch.Generator) -> SquashedPolicy:
    """A random RBF policy for collecting data: support points ~ N(0, I) in feature space, wide targets."""
    targets = RANDOM_POLICY_TARGET_STD * torch.randn(num_basis, task.action_dim, generator=generator,
                                                     dtype=torch.float64)
    inner = RBFPolicy(task.feature_dim, task.action_dim, num_basis, targets=targets, generator=generator)
    return SquashedPolicy(inner, torch.as_tensor(task.action_bound, dtype=torch.float64))


def collect(task: Task, num_basis: int, n: int, seed: int) -> TransitionDataset:
    """n real transitions: random-action and random-RBF-policy episodes in turn, the last one cut."""
    features = AngleFeatures(task.state_dim, task.angle_dims)
    data = TransitionDataset(task.state_dim, task.action_dim, task.angle_dims)
    env = task.make_env()
    try:
        episode = 0
        while len(data) < n:
            if episode % 2 == 0:
                actor = random_actor(task, np.random.default_rng(derive_seed(seed, episode, DATA_POLICY_STREAM)))
            else:
                policy = data_policy(task, num_basis, torch_generator(seed, episode, DATA_POLICY_STREAM))
                actor = policy_actor(policy, features, torch.float64)
            real = run_episode(env, task, actor, derive_seed(seed, episode, ENV_STREAM))
            keep = min(len(real.actions), n - len(data))
            data.add_episode(real.states[: keep + 1], real.actions[:keep])
            episode += 1
    finally:
        env.close()
    return data


def model_path(cfg: DictConfig, n: int, seed: int, cache_dir: Path) -> Path:
    """Where the fitted model of n tuples of this task and seed is cached."""
    key = json.dumps({"task": OmegaConf.to_container(cfg.task, resolve=True), "n": n, "seed": seed,
                      "restarts": MODEL_FIT_RESTARTS, "version": DATA_VERSION}, sort_keys=True)
    return cache_dir / f"{cfg.task.name}_n{n}_seed{seed}_{hashlib.sha1(key.encode()).hexdigest()[:10]}.pt"


def ensure_model(cfg: DictConfig, n: int, seed: int, cache_dir: Path) -> tuple[Path, dict[str, Any]]:
    """The cached model of n tuples (fitted and saved first if missing) and how it was made."""
    path = model_path(cfg, n, seed, cache_dir)
    info_path = path.with_suffix(".json")
    if path.exists() and info_path.exists():
        return path, {**json.loads(info_path.read_text()), "cached": True}
    task = build(cfg).task
    data = collect(task, int(cfg.task.policy_size), n, seed)
    inputs, targets = gp_training_pairs(data, AngleFeatures(task.state_dim, task.angle_dims), torch.float64)
    model = DynamicsGP(inputs, targets)
    tic = time.perf_counter()
    model.fit(restarts=MODEL_FIT_RESTARTS, max_iter=int(cfg.model.max_iter),
              generator=torch.Generator().manual_seed(seed))
    theta = model.hyperparameters
    info = {"n": len(data), "episodes": data.num_episodes, "fit_s": time.perf_counter() - tic,
            "fit_restarts": MODEL_FIT_RESTARTS, "fit_max_iter": int(cfg.model.max_iter), "dtype": "float64",
            "signal_variance": theta.signal_variance.tolist(), "noise_variance": theta.noise_variance.tolist(),
            "snr": (theta.signal_variance / theta.noise_variance).sqrt().tolist()}
    path.parent.mkdir(parents=True, exist_ok=True)
    model.save(path)
    info_path.write_text(json.dumps(info, indent=2) + "\n")
    return path, {**info, "cached": False}


def rollout_and_gradient(propagator: Propagator, start: Gaussian, horizon: int) -> float:
    """One rollout of H steps and the gradient of V w.r.t. ψ; returns V."""
    propagator.policy.zero_grad()
    value = propagator.expected_return(start, horizon)
    value.backward()
    return float(value.detach())


def batched_round(parts: Parts, model: DynamicsGP, policy: SquashedPolicy,
                  seed: int) -> tuple[Callable[[], None], int]:
    """One round of the search as a call: the rollout + gradient of its R starting points at once (ψ `R x ...`); R."""
    states = parts.search.starting_states(policy, torch_generator(seed, SEARCH_EPISODE, SEARCH_STREAM))
    batched = batched_policy(policy, len(states))
    set_psi(batched, stack_psi(states, psi_names(policy)), (len(states),))
    propagator = parts.make_propagator(model, batched, parts.reward, angle_dims=parts.task.angle_dims)

    def round_() -> None:
        batched.zero_grad()
        propagator.expected_return(parts.start, parts.task.horizon).sum().backward()

    return round_, len(states)


def batched_rollout_grad(parts: Parts, model: DynamicsGP, policy: SquashedPolicy, seed: int,
                         repeats: int) -> dict[str, Any]:
    """One rollout + gradient of the search's R starting points at once (ψ `R x ...`): median time and R."""
    round_, restarts = batched_round(parts, model, policy, seed)
    times = []
    for _ in range(repeats + 1):  # the first is a warm-up
        tic = time.perf_counter()
        round_()
        times.append(time.perf_counter() - tic)
    return {"batched_rollout_grad_s_median": statistics.median(times[1:]), "batched_restarts": restarts}
