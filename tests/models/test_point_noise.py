"""Per-point noise σ_ε² + c_ei (source samples weighted by relevance): posterior, evidence, limits, checkpoints."""

from __future__ import annotations

import math

import pytest
import torch

from qtl.models import DynamicsGP, GPHyperparameters
from qtl.models.point_noise import checked_extra_noise

DTYPE = torch.float64


def data(n: int = 24, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Inputs `n x 3` and two smooth noisy targets `n x 2`."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 3, generator=gen, dtype=DTYPE)
    y = torch.stack([x[:, 0].sin(), x[:, 1] * x[:, 2]], dim=-1)
    return x, y + 0.05 * torch.randn(n, 2, generator=gen, dtype=DTYPE)


THETA = GPHyperparameters(lengthscales=torch.tensor([[1.0, 1.5, 0.8], [0.9, 1.1, 1.3]], dtype=DTYPE),
                          signal_variance=torch.tensor([0.7, 1.2], dtype=DTYPE),
                          noise_variance=torch.tensor([0.01, 0.02], dtype=DTYPE))


def se(a: torch.Tensor, b: torch.Tensor, lengthscales: torch.Tensor, alpha2: float) -> torch.Tensor:
    """The SE kernel of Eq. 3 by hand: `len(a) x len(b)`."""
    diff = (a[:, None, :] - b[None, :, :]) / lengthscales
    return alpha2 * torch.exp(-0.5 * diff.square().sum(-1))


def extras(n: int, seed: int = 1) -> torch.Tensor:
    """Extra noise c >= 0 `n x 2`, a third of them 0."""
    gen = torch.Generator().manual_seed(seed)
    c = 0.5 * torch.rand(n, 2, generator=gen, dtype=DTYPE)
    c[::3] = 0.0
    return c


def test_the_posterior_with_per_point_noise_equals_the_hand_formula():
    x, y = data()
    c = extras(len(x))
    model = DynamicsGP(x, y, THETA, extra_noise=c)
    test = torch.randn(7, 3, generator=torch.Generator().manual_seed(5), dtype=DTYPE)
    mean, var = model.predict(test)
    cache = model.posterior_cache()
    for e in range(2):
        ls, a2, sn2 = THETA.lengthscales[e], float(THETA.signal_variance[e]), float(THETA.noise_variance[e])
        K = se(x, x, ls, a2) + torch.diag(sn2 + c[:, e])
        k = se(test, x, ls, a2)
        beta = torch.linalg.solve(K, y[:, e])
        torch.testing.assert_close(mean[:, e], k @ beta, rtol=1e-9, atol=1e-10)
        torch.testing.assert_close(var[:, e], a2 - (k * torch.linalg.solve(K, k.T).T).sum(-1), rtol=1e-7, atol=1e-10)
        torch.testing.assert_close(cache.beta[e], beta, rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(cache.K_inv[e], torch.linalg.inv(K), rtol=1e-8, atol=1e-8)
    torch.testing.assert_close(cache.extra_noise, c.T)
    _, noisy = model.predict(test, include_noise=True)
    torch.testing.assert_close(noisy, var + THETA.noise_variance, rtol=0, atol=1e-15)


def test_the_evidence_with_per_point_noise_equals_the_hand_log_density():
    x, y = data()
    c = extras(len(x))
    model = DynamicsGP(x, y, THETA, extra_noise=c)
    model.train()
    with torch.no_grad():
        value = model.log_evidence() * len(x) - model.log_prior()  # `E`: log N(y; 0, K + σ² S)
    for e in range(2):
        ls, a2, sn2 = THETA.lengthscales[e], float(THETA.signal_variance[e]), float(THETA.noise_variance[e])
        K = se(x, x, ls, a2) + torch.diag(sn2 + c[:, e])
        expected = torch.distributions.MultivariateNormal(torch.zeros(len(x), dtype=DTYPE), K).log_prob(y[:, e])
        torch.testing.assert_close(value[e], expected, rtol=1e-9, atol=1e-8)


def test_no_extra_noise_pools_the_data_bit_for_bit_in_the_cache():
    x, y = data()
    plain = DynamicsGP(x, y, THETA)
    pooled = DynamicsGP(x, y, THETA, extra_noise=torch.zeros(len(x), dtype=DTYPE))
    a, b = plain.posterior_cache(), pooled.posterior_cache()
    torch.testing.assert_close(b.beta, a.beta, rtol=0, atol=1e-15)
    torch.testing.assert_close(b.K_inv, a.K_inv, rtol=0, atol=1e-12)
    torch.testing.assert_close(pooled.predict(x[:5])[1], plain.predict(x[:5])[1], rtol=0, atol=1e-14)


def test_vanishing_relevance_leaves_the_target_data_alone():
    x, y = data(30)
    own, source = 18, 12
    target = DynamicsGP(x[:own], y[:own], THETA)
    c = torch.zeros(len(x), dtype=DTYPE)
    c[own:] = 1e8  # σ̂² (1/w − 1) with w ~ 1e-10
    weighted = DynamicsGP(x, y + torch.cat([torch.zeros(own, 2), torch.full((source, 2), 3.0)]).to(DTYPE), THETA,
                          extra_noise=c)
    test = torch.randn(9, 3, generator=torch.Generator().manual_seed(2), dtype=DTYPE)
    for got, want in zip(weighted.predict(test), target.predict(test), strict=True):
        torch.testing.assert_close(got, want, rtol=0, atol=1e-6)  # the samples' pull is O(w · 3)


def test_head_is_the_target_part_at_the_same_theta():
    x, y = data(30)
    c = torch.zeros(30, dtype=DTYPE)
    c[20:] = 4.0
    head = DynamicsGP(x, y, THETA, extra_noise=c).head(20)
    assert head.extra_noise is None and len(head.train_x) == 20
    torch.testing.assert_close(head.predict(x[:3])[0], DynamicsGP(x[:20], y[:20], THETA).predict(x[:3])[0])


def test_a_checkpoint_round_trip_keeps_the_scales(tmp_path):
    x, y = data()
    c = extras(len(x))
    model = DynamicsGP(x, y, THETA, extra_noise=c)
    model.save(tmp_path / "gp.pt")
    loaded = DynamicsGP.load(tmp_path / "gp.pt")
    torch.testing.assert_close(loaded.extra_noise, model.extra_noise, rtol=0, atol=0)
    assert "extra_noise" not in DynamicsGP(x, y, THETA).state()  # homoscedastic checkpoints unchanged


def test_fitting_moves_sigma_and_keeps_the_scales():
    x, y = data()
    c = extras(len(x))
    model = DynamicsGP(x, y, extra_noise=c)
    model.fit(restarts=1, max_iter=20)
    torch.testing.assert_close(model.extra_noise, c.T, rtol=0, atol=0)
    assert math.isfinite(float(model.fit_objective.sum()))


@pytest.mark.parametrize("bad", [torch.full((24, 2), -0.5), torch.full((24, 2), math.inf), torch.ones(23)])
def test_bad_scales_are_refused(bad):
    with pytest.raises(ValueError, match="extra_noise"):
        checked_extra_noise(bad.to(DTYPE), 24, 2)


def test_vanishing_relevance_leaves_the_evidence_of_theta_to_the_target_data():
    """With c → ∞ the source tuples add a constant to the log evidence: θ's objective is the target's alone."""
    x, y = data(40)
    own = 24
    shifted = y.clone()
    shifted[own:] += 2.0  # source tuples that contradict the target's
    c = torch.zeros(40, dtype=DTYPE)
    c[own:] = 1e10
    weighted, target = DynamicsGP(x, shifted, extra_noise=c), DynamicsGP(x[:own], y[:own])
    for name in ("input_std", "target_var"):  # the same data-centred priors
        getattr(weighted, name).copy_(getattr(target, name))

    def gap(theta: GPHyperparameters) -> float:
        for model in (weighted, target):
            model.hyperparameters = theta
            model.train()
        with torch.no_grad():
            return float((weighted.log_evidence() * 40 - target.log_evidence() * own).sum())

    other = GPHyperparameters(THETA.lengthscales * 1.7, THETA.signal_variance * 0.4, THETA.noise_variance * 3.0)
    assert abs(gap(THETA) - gap(other)) < 1e-6  # the same objective up to a constant: the same θ_p
    plain = DynamicsGP(x, shifted)
    for name in ("input_std", "target_var"):
        getattr(plain, name).copy_(getattr(target, name))
    plain.hyperparameters, target.hyperparameters = THETA, THETA
    with torch.no_grad():
        pooled_gap = [float((plain.log_evidence() * 40 - target.log_evidence() * own).sum())]
        plain.hyperparameters, target.hyperparameters = other, other
        pooled_gap.append(float((plain.log_evidence() * 40 - target.log_evidence() * own).sum()))
    assert abs(pooled_gap[0] - pooled_gap[1]) > 1.0  # pooled, the contradicting tuples do move it
