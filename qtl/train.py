"""``qtl-train``: the Hydra entry point."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import gymnasium
import hydra
import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig
from torch.utils.tensorboard import SummaryWriter

import envs  # noqa: F401  (registers the qtl/ environment ids)
from envs.rewards import augment_angles
from qtl.config import register_configs
from qtl.data import TransitionDataset
from qtl.models import DynamicsGP
from qtl.seeding import seed_everything

log = logging.getLogger(__name__)

DTYPES = {"float64": torch.float64, "float32": torch.float32}


@dataclass(frozen=True)
class FitResult:
    """What the dynamics-fit job measured."""

    train_points: int
    test_points: int
    rmse: list[float]  # per output dimension, held-out
    smse: list[float]  # held-out MSE / variance of the held-out targets
    noise_std: list[float]
    fit_seconds: float


def random_episode(env: gymnasium.Env, rng: np.random.Generator, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """One episode of actions uniform in the action bounds: states `T+1 x D`, actions `T x F`."""
    obs, _ = env.reset(seed=seed)
    states, actions = [obs], []
    low, high = env.action_space.low, env.action_space.high
    while True:
        action = rng.uniform(low, high).astype(env.action_space.dtype)
        obs, _, terminated, truncated, _ = env.step(action)
        states.append(obs)
        actions.append(action)
        if terminated or truncated:
            return np.asarray(states), np.asarray(actions)


def gp_pairs(data: TransitionDataset, angle_dims: list[int], dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """GP inputs [features(x_t), u_t] `n x (D_aug + F)` and targets Δ_t `n x D`."""
    x, u, delta = data.tensors(dtype)
    features = torch.as_tensor(augment_angles(x.numpy(), angle_dims), dtype=dtype)
    return torch.cat([features, u], dim=-1), delta


def fit_dynamics(cfg: DictConfig, output_dir: Path) -> FitResult:
    """Record random episodes, fit the dynamics GP, report its held-out fit."""
    dtype = DTYPES[cfg.dtype]
    rng = seed_everything(cfg.seed)
    env = gymnasium.make(cfg.env.id, **cfg.env.kwargs)
    if not isinstance(env.observation_space, gymnasium.spaces.Box) or not isinstance(
        env.action_space, gymnasium.spaces.Box
    ):
        raise ValueError(f"{cfg.env.id} must have Box observation and action spaces")
    state_dim, action_dim = env.observation_space.shape[0], env.action_space.shape[0]
    train = TransitionDataset(state_dim, action_dim)
    test = TransitionDataset(state_dim, action_dim)
    for i in range(cfg.train_episodes + cfg.test_episodes):
        target = train if i < cfg.train_episodes else test
        target.add_episode(*random_episode(env, rng, seed=cfg.seed + i))
    env.close()

    train_x, train_y = gp_pairs(train, list(cfg.angle_dims), dtype)
    test_x, test_y = gp_pairs(test, list(cfg.angle_dims), dtype)
    model = DynamicsGP(train_x, train_y, dtype=dtype)
    start = time.perf_counter()
    model.fit(
        restarts=cfg.model.restarts,
        max_iter=cfg.model.max_iter,
        generator=torch.Generator().manual_seed(cfg.seed),
    )
    fit_seconds = time.perf_counter() - start
    mean, _ = model.predict(test_x)
    mse = ((mean - test_y) ** 2).mean(dim=0)
    theta = model.hyperparameters
    result = FitResult(
        train_points=len(train),
        test_points=len(test),
        rmse=mse.sqrt().tolist(),
        smse=(mse / test_y.var(dim=0)).tolist(),
        noise_std=theta.noise_variance.sqrt().tolist(),
        fit_seconds=fit_seconds,
    )

    model.save(output_dir / "dynamics_gp.pt")
    writer = SummaryWriter(log_dir=str(output_dir))
    try:
        for j in range(model.num_outputs):
            writer.add_scalar(f"model/rmse/out{j}", result.rmse[j], 0)
            writer.add_scalar(f"model/smse/out{j}", result.smse[j], 0)
        for name, value in theta.as_dict().items():
            writer.add_scalar(f"model/{name}", value, 0)
        writer.add_scalar("time/model_fit_s", fit_seconds, 0)
    finally:
        writer.close()

    log.info("fitted %d-output GP on %d transitions in %.1f s", model.num_outputs, len(train), fit_seconds)
    for j in range(model.num_outputs):
        log.info(
            "Δx[%d]: held-out RMSE %.4g, SMSE %.4f, noise std %.3g, signal std %.3g",
            j, result.rmse[j], result.smse[j], result.noise_std[j],
            float(theta.signal_variance[j].sqrt()),
        )
    log.info("wrote %s", output_dir)
    return result


register_configs()


@hydra.main(version_base="1.3", config_path="pkg://qtl.configs", config_name="train")
def main(cfg: DictConfig) -> None:
    """Run the configured job in Hydra's output directory."""
    torch.set_default_dtype(DTYPES[cfg.dtype])
    fit_dynamics(cfg, Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":
    main()
