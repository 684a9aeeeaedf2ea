"""A per-particle reference of marginal particle paths: the GP posterior at each particle, the propagator's noise."""

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
