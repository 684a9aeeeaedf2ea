"""Task compliance Λ (Eq. 14): leave-one-out predictive, tempering, input checks, mountain-car power."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch

import qtl.envs  # noqa: F401  (registers the ids)
from qtl.data import TransitionDataset, gp_training_pairs
from qtl.features import AngleFeatures
from qtl.models import DynamicsGP
from qtl.transfer.compliance import Compliance, leave_one_out, task_compliance

DTYPE = torch.float64
ENV_ID = "qtl/MountainCar-v0"
# Mountain car: the source GP sees SOURCE_EPISODES random episodes of the default horizon; each
# target GP sees TARGET_EPISODES shorter episodes from other seeds (TARGET_EPISODES x TARGET_HORIZON tuples).
SOURCE_EPISODES = 3
TARGET_EPISODES = 2
TARGET_HORIZON = 60
FIT_RESTARTS = 2
# Measured over base seeds 0-19: Λ(100 % → 100 %) in [0.515, 0.617], Λ(100 % → 300 %) in [0.000, 0.022].
SAME_SYSTEM_MIN = 0.45
OTHER_SYSTEM_MAX = 0.35
MIN_GAP = 0.15


# ---- leave-one-out predictive -------------------------------------------------------------------
@pytest.mark.parametrize("held_out", [0, 7, 18, 29])
def test_leave_one_out_equals_refit_without_the_point(gp_factory, held_out: int) -> None:
    model = gp_factory(30, 2, 1, seed=3)  # n = 30, D = 3, E = 2
    loo_mean, loo_var = leave_one_out(model)
    assert loo_mean.shape == loo_var.shape == (30, 2)
    assert loo_mean.dtype == loo_var.dtype == DTYPE

    keep = torch.arange(30) != held_out
    refit = DynamicsGP(model.train_x[keep], model.train_y[keep], model.hyperparameters)
    mean, var = refit.predict(model.train_x[held_out : held_out + 1], include_noise=True)
    torch.testing.assert_close(loo_mean[held_out], mean[0], rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(loo_var[held_out], var[0], rtol=1e-8, atol=1e-12)
    # Noisy predictive: never below the noise variance.
    assert (loo_var >= model.hyperparameters.noise_variance).all()


# ---- Λ and its terms ----------------------------------------------------------------------------
def test_compliance_terms_are_the_documented_densities(gp_factory) -> None:
    source, target = gp_factory(40, 2, 1, seed=0), gp_factory(30, 2, 1, seed=1, lengthscale=1.0)
    result = task_compliance(source, target)
    assert isinstance(result, Compliance)
    for tensor in (result.probabilities, result.log_source, result.log_target):
        assert tensor.shape == (30,)
        assert tensor.dtype == DTYPE

    mean, var = source.predict(target.train_x, include_noise=True)
    log_source = torch.distributions.Normal(mean, var.sqrt()).log_prob(target.train_y).sum(-1)
    loo_mean, loo_var = leave_one_out(target)
    log_target = torch.distributions.Normal(loo_mean, loo_var.sqrt()).log_prob(target.train_y).sum(-1)
    torch.testing.assert_close(result.log_source, log_source, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(result.log_target, log_target, rtol=1e-10, atol=1e-10)

    expected = torch.sigmoid((log_source - log_target) / result.temperature)
    torch.testing.assert_close(result.probabilities, expected, rtol=1e-10, atol=1e-12)
    assert ((result.probabilities >= 0) & (result.probabilities <= 1)).all()
    assert result.value == pytest.approx(result.probabilities.mean().item(), abs=1e-12)
    # The two models differ: not every tuple sits at the indifference point.
    assert (result.probabilities - 0.5).abs().max() > 0.05


def test_larger_temperature_pulls_every_probability_toward_one_half(gp_factory) -> None:
    source, target = gp_factory(40, 3, 1, seed=0), gp_factory(25, 3, 1, seed=2, lengthscale=1.0)
    default = task_compliance(source, target)
    assert default.temperature == target.num_outputs == 3
    explicit = task_compliance(source, target, temperature=3.0)
    torch.testing.assert_close(default.probabilities, explicit.probabilities, rtol=0, atol=0)

    ratio = default.log_source - default.log_target
    assert (ratio.abs() > 1e-6).all()
    distances = [
        (task_compliance(source, target, temperature=kappa).probabilities - 0.5).abs()
        for kappa in (0.25, 1.0, 3.0, 10.0, 100.0)
    ]
    for closer, farther in zip(distances[1:], distances[:-1], strict=True):
        assert (closer < farther).all()
    assert distances[-1].max() < 0.5 * distances[0].max()


def test_resolution_adds_the_documented_variance_floor(gp_factory) -> None:
    source, target = gp_factory(40, 2, 1, seed=0), gp_factory(30, 2, 1, seed=1, lengthscale=1.0)
    exact = task_compliance(source, target)
    torch.testing.assert_close(task_compliance(source, target, resolution=0.0).probabilities, exact.probabilities,
                               rtol=0, atol=0)
    rho = 0.2
    result = task_compliance(source, target, resolution=rho)
    assert result.resolution == rho
    floor = rho**2 * target.train_y.var(dim=0, correction=0)  # E: ρ² s_a²
    mean, var = source.predict(target.train_x, include_noise=True)
    log_source = torch.distributions.Normal(mean, (var + floor).sqrt()).log_prob(target.train_y).sum(-1)
    loo_mean, loo_var = leave_one_out(target)
    log_target = torch.distributions.Normal(loo_mean, (loo_var + floor).sqrt()).log_prob(target.train_y).sum(-1)
    torch.testing.assert_close(result.log_source, log_source, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(result.log_target, log_target, rtol=1e-10, atol=1e-10)
    # A resolution far coarser than any prediction error cannot tell the hypotheses apart.
    coarse = task_compliance(source, target, resolution=1e4)
    assert (coarse.probabilities - 0.5).abs().max() < 1e-3


# ---- input checks -------------------------------------------------------------------------------
def _random_gp(n: int, input_dim: int, output_dim: int, seed: int) -> DynamicsGP:
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(n, input_dim, generator=gen, dtype=DTYPE)
    y = torch.sin(x.sum(-1, keepdim=True) + torch.arange(output_dim, dtype=DTYPE))
    return DynamicsGP(x, y)


def _forbid_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make any prediction or solve fail the test: the checks must come before any work."""

    def fail(*_args, **_kwargs):
        raise AssertionError("task_compliance did work before validating its arguments")

    monkeypatch.setattr(DynamicsGP, "predict", fail)
    monkeypatch.setattr(DynamicsGP, "posterior_cache", fail)


@pytest.mark.parametrize(
    ("source_dims", "target_dims"),
    [((3, 2), (4, 2)), ((3, 2), (3, 3)), ((4, 3), (3, 2))],
)
def test_mismatched_dimensions_raise(monkeypatch, source_dims, target_dims) -> None:
    source, target = _random_gp(10, *source_dims, seed=0), _random_gp(10, *target_dims, seed=1)
    _forbid_work(monkeypatch)
    message = (
        f"source GP has D={source_dims[0]} inputs and E={source_dims[1]} outputs, "
        f"target GP has D={target_dims[0]} inputs and E={target_dims[1]} outputs"
    )
    with pytest.raises(ValueError, match=message):
        task_compliance(source, target)


@pytest.mark.parametrize("temperature", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_temperature_raises(monkeypatch, temperature: float) -> None:
    source, target = _random_gp(10, 3, 2, seed=0), _random_gp(10, 3, 2, seed=1)
    _forbid_work(monkeypatch)
    with pytest.raises(ValueError, match="temperature must be finite and > 0"):
        task_compliance(source, target, temperature=temperature)


@pytest.mark.parametrize("resolution", [-0.1, float("nan"), float("inf")])
def test_bad_resolution_raises(monkeypatch, resolution: float) -> None:
    source, target = _random_gp(10, 3, 2, seed=0), _random_gp(10, 3, 2, seed=1)
    _forbid_work(monkeypatch)
    with pytest.raises(ValueError, match="resolution must be finite and >= 0"):
        task_compliance(source, target, resolution=resolution)


# ---- mountain car: same system vs 300 % engine power ------------------------------------------
def _random_action_model(power: float, seeds: list[int], horizon: int | None, fit_seed: int) -> DynamicsGP:
    """A GP fitted on uniform-random-action episodes of mountain car at ``power``, one per seed."""
    kwargs = {"power": power} if horizon is None else {"power": power, "horizon": horizon}
    env = gymnasium.make(ENV_ID, **kwargs)
    data = TransitionDataset(2, 1)
    for seed in seeds:
        rng = np.random.default_rng(seed)
        obs, _ = env.reset(seed=seed)
        states, actions, done = [obs], [], False
        while not done:
            action = rng.uniform(-1.0, 1.0, size=1)
            obs, _, terminated, truncated, _ = env.step(action)
            states.append(obs)
            actions.append(action)
            done = terminated or truncated
        data.add_episode(np.asarray(states), np.asarray(actions))
    inputs, targets = gp_training_pairs(data, AngleFeatures(2), DTYPE)  # mountain car has no angle dims
    model = DynamicsGP(inputs, targets)
    model.fit(restarts=FIT_RESTARTS, generator=torch.Generator().manual_seed(fit_seed))
    return model


@pytest.mark.parametrize("base", [0, 1, 2])
def test_mountain_car_compliance_drops_at_300_percent_power(base: int) -> None:
    source = _random_action_model(1.0, [100 * base + i for i in range(SOURCE_EPISODES)], None, base)
    target_seeds = [100 * base + 50 + i for i in range(TARGET_EPISODES)]
    same = task_compliance(source, _random_action_model(1.0, target_seeds, TARGET_HORIZON, base))
    other = task_compliance(source, _random_action_model(3.0, target_seeds, TARGET_HORIZON, base))
    assert same.probabilities.shape == other.probabilities.shape == (TARGET_EPISODES * TARGET_HORIZON,)
    assert same.value >= SAME_SYSTEM_MIN, f"same system: Λ = {same.value:.3f}"
    assert other.value < OTHER_SYSTEM_MAX, f"300 % power: Λ = {other.value:.3f}"
    assert same.value - other.value >= MIN_GAP, f"Λ same {same.value:.3f} vs 300 % {other.value:.3f}"
