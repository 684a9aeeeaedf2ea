"""What a propagator is handed: the round-off guard of low-precision propagation."""

from __future__ import annotations

import logging

import pytest
import torch

from qtl.models import GPPosteriorCache
from qtl.models.hyperparameters import GPHyperparameters
from qtl.policies import LinearPolicy
from qtl.propagation import MomentMatching, Particles
from qtl.propagation.gp_cache import variance_roundoff_bound
from tests.helpers import quadratic_reward

N = 100


def _cache(noise_variance: float) -> GPPosteriorCache:
    """A 2-D state, 1-D action GP cache with α² = 1 and the given σ_ε² (the tensors' values do not matter)."""
    theta = GPHyperparameters(torch.ones(2, 3, dtype=torch.float64), torch.ones(2, dtype=torch.float64),
                              torch.full((2,), noise_variance, dtype=torch.float64))
    eye = torch.eye(N, dtype=torch.float64).expand(2, N, N)
    return GPPosteriorCache(torch.zeros(N, 3, dtype=torch.float64), eye, torch.zeros(2, N, dtype=torch.float64),
                            theta)


def test_roundoff_bound_is_eps_n_alpha4_over_noise():
    data = {"inputs": torch.zeros(N, 3), "signal_variance": torch.tensor([2.0]), "noise_variance": torch.tensor([1e-3])}
    expected = torch.finfo(torch.float32).eps * N * 4.0 / 1e-3
    torch.testing.assert_close(variance_roundoff_bound(data, torch.float32), torch.tensor([expected]))


@pytest.mark.parametrize("propagator", [MomentMatching, Particles])
@pytest.mark.parametrize(("noise_variance", "dtype", "warns"), [
    (1e-4, torch.float32, True),  # ε n α⁴/σ² = 1.2e-7 · 100 / 1e-4 = 0.12 > 1e-4
    (1e-2, torch.float32, False),  # 1.2e-3 < 1e-2
    (1e-4, torch.float64, False),  # 2.2e-16 · 100 / 1e-4 = 2.2e-10 < 1e-4
])
def test_low_precision_propagation_warns_when_variances_lose_their_digits(caplog, propagator, noise_variance, dtype,
                                                                           warns):
    policy = LinearPolicy(2, 1).to(dtype)
    with caplog.at_level(logging.WARNING, logger="qtl.propagation.gp_cache"):
        propagator(_cache(noise_variance), policy, quadratic_reward(2), dtype=dtype)
    assert any("use dtype=float64" in r.getMessage() for r in caplog.records) == warns


@pytest.mark.parametrize("propagator", [MomentMatching, Particles])
def test_float64_warning_does_not_advise_float64(caplog, propagator):
    # ε n α⁴/σ² = 2.2e-16 · 100 / 1e-9 = 2.2e-5 > 1e-9: even float64 cannot resolve the variances.
    policy = LinearPolicy(2, 1).to(torch.float64)
    with caplog.at_level(logging.WARNING, logger="qtl.propagation.gp_cache"):
        propagator(_cache(1e-9), policy, quadratic_reward(2), dtype=torch.float64)
    messages = [r.getMessage() for r in caplog.records]
    assert any("propagation in float64" in m for m in messages)
    assert not any("use dtype=float64" in m for m in messages)
    assert any("α/σ_ε up to 3.16e+04" in m for m in messages)
