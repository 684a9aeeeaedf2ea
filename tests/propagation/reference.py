"""References for propagation tests: marginal particle paths per particle, and draws of a step's joint Gaussian."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from qtl.features import AngleFeatures
from qtl.gaussian import Gaussian
from qtl.propagation import Particles

# Agreement of particles with an independent per-particle reference using the same noise.
EXACT_RTOL, EXACT_ATOL = 1e-9, 1e-12


def assert_marginal_paths(particles: Particles, gp, policy, start: Gaussian, horizon: int, posterior: Callable,
                          include_noise: bool, step: Callable[[Tensor, Tensor], Tensor] = torch.add) -> None:
    """``particles``' states and actions equal a recomputation per particle: u = π(φ(x)), x' = step(x, m + √v ε_t).

    ``posterior``: the conftest GP posterior (checked against GPyTorch); Δ `P x D` has every output's draw (``step``
    picks what it uses).
    """
    features = AngleFeatures(particles.state_dim, particles.features.angle_dims)
    cache = gp.posterior_cache()
    with torch.no_grad():
        states, actions = particles.trajectories(start, horizon)
        start_noise, step_noise, _ = particles.base_noise(horizon)
        x = start.mean + start_noise @ torch.linalg.cholesky(start.cov).mT
        expected = [x]
        for t in range(horizon):
            u = policy(features(x))
            torch.testing.assert_close(actions[:, t], u, rtol=EXACT_RTOL, atol=EXACT_ATOL)
            mean, var = posterior(cache, torch.cat([features(x), u], dim=-1))
            var = var.clamp_min(0.0) + (cache.hyperparameters.noise_variance if include_noise else 0.0)
            x = step(x, mean + var.sqrt() * step_noise[t])
            expected.append(x)
    torch.testing.assert_close(states, torch.stack(expected, dim=1), rtol=EXACT_RTOL, atol=EXACT_ATOL)


def joint_draws(joint: tuple[Tensor, ...], count: int, generator: torch.Generator,
                noise_variance: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``count`` draws of (x_t, Δ) from the joint Gaussian a recorded step: x `count x D`, Δ `count x E'`.

    ``joint``: (μ, Σ, μ_Δ, Σ_Δ, cov[x, Δ]) as ``moment_terms`` receives them; ``noise_variance`` `E'`: σ_ε², added to Δ
    as independent noise (a step with ``include_noise``), drawn after the joint from the same ``generator``.
    """
    mean, cov, delta_mean, delta_cov, cross = joint
    joint_mean = torch.cat([mean, delta_mean])
    joint_cov = torch.cat([torch.cat([cov, cross], 1), torch.cat([cross.T, delta_cov], 1)], 0)
    draws = joint_mean + torch.randn(count, len(joint_mean), generator=generator, dtype=mean.dtype) @ \
        torch.linalg.cholesky(joint_cov).T
    x, delta = draws[:, :len(mean)], draws[:, len(mean):]
    if noise_variance is not None:
        delta = delta + torch.randn(count, len(delta_mean), generator=generator, dtype=mean.dtype) * \
            noise_variance.sqrt()
    return x, delta
