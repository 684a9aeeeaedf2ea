"""Source samples weighted by relevance (issue 65): w, the weighted data, the plan, and runs through the loop."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from qtl.build import build, transfer_plan
from qtl.checkpoint import latest_checkpoint, load_checkpoint
from qtl.data import TransitionDataset
from qtl.errors import TransferError
from qtl.features import AngleFeatures
from qtl.gaussian import Gaussian
from qtl.loop import run
from qtl.models import DynamicsGP, GPHyperparameters
from qtl.propagation import MomentMatching
from qtl.task import Task
from qtl.transfer import SourceRun
from qtl.transfer.samples import (
    EFFECTIVE_SAMPLES,
    MIN_RELEVANCE,
    RELEVANCE,
    SOURCE_SAMPLES,
    SourceSamples,
    WeightedSamples,
    local_relevance,
    relevance,
    source_trust,
)
from tests.helpers import PARTICLES_TINY, TINY, tiny_config, train_config

DTYPE = torch.float64
HEAVY = "task.env.pole_mass=2.0"


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def toy(n: int, seed: int, shift: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Inputs `n x 2` and one smooth target `n x 1` (plus ``shift``)."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 2, generator=gen, dtype=DTYPE)
    return x, (x[:, :1].sin() + shift) + 0.01 * torch.randn(n, 1, generator=gen, dtype=DTYPE)


THETA = GPHyperparameters(torch.tensor([[1.0, 1.0]], dtype=DTYPE), torch.tensor([1.0], dtype=DTYPE),
                          torch.tensor([1e-4], dtype=DTYPE))


def test_local_relevance_is_the_target_predictive_density_over_its_peak_and_coverage_its_variance_cut():
    x, y = toy(30, 0)
    sx, sy = toy(7, 1, shift=0.02)
    target = DynamicsGP(x, y, THETA)
    local, coverage = local_relevance(target, sx, sy)
    mean, var = target.predict(sx, include_noise=True)
    density = torch.distributions.Normal(mean, var.sqrt())
    expected = (density.log_prob(sy) - density.log_prob(mean)).exp()
    torch.testing.assert_close(local, expected, rtol=1e-12, atol=1e-300)
    _, latent = target.predict(sx)
    torch.testing.assert_close(coverage, 1 - latent / THETA.signal_variance, rtol=1e-9, atol=1e-12)
    assert local.shape == coverage.shape == (7, 1) and bool((local > 0).all()) and bool((local <= 1).all())
    far = torch.full((1, 2), 30.0, dtype=DTYPE)
    assert float(local_relevance(target, x[:1], y[:1])[1]) > 0.99  # at a target tuple: covered
    assert float(local_relevance(target, far, torch.zeros(1, 1, dtype=DTYPE))[1]) < 1e-9  # far from all: not


def test_relevance_is_local_where_covered_and_the_source_trust_where_not():
    x, y = toy(30, 0)
    sx, sy = toy(9, 1, shift=0.3)
    target = DynamicsGP(x, y, THETA)
    local, coverage = local_relevance(target, sx, sy)
    trust = (math.sqrt(2) * (coverage * local).sum(0) + 1) / (coverage.sum(0) + 1)
    torch.testing.assert_close(source_trust(local, coverage), trust.clamp(max=1.0), rtol=1e-12, atol=0)
    torch.testing.assert_close(relevance(x, y, sx, sy, THETA),
                               (coverage * local + (1 - coverage) * trust.clamp(max=1.0)).clamp_min(MIN_RELEVANCE),
                               rtol=1e-12, atol=0)
    # No tuple covered: the pseudo-tuple's full trust.
    nothing = torch.zeros(5, 2, dtype=DTYPE)
    torch.testing.assert_close(source_trust(torch.rand(5, 2, dtype=DTYPE), nothing), torch.ones(2, dtype=DTYPE))


@pytest.mark.parametrize("offset", [0.0, 1.0, 2.0])
def test_source_trust_is_one_for_a_matching_source_and_exp_minus_b2_over_4_off_by_b_monte_carlo(offset):
    """Source Δ drawn from the target's predictive at covered inputs, shifted by ``offset`` standard deviations."""
    gen = torch.Generator().manual_seed(3)
    x = torch.linspace(-3, 3, 40, dtype=DTYPE)[:, None].expand(40, 2).contiguous()
    target = DynamicsGP(x, x[:, :1].sin(), THETA)
    sx = x[:-1] + 0.5 * (x[1:] - x[:-1])  # between the target's inputs: covered
    mean, var = target.predict(sx, include_noise=True)
    draws = 4000
    sx = sx.repeat(draws // len(sx) + 1, 1)[:draws]
    mean, var = mean.repeat(draws // len(mean) + 1, 1)[:draws], var.repeat(draws // len(var) + 1, 1)[:draws]
    sy = mean + var.sqrt() * (offset + torch.randn(mean.shape, generator=gen, dtype=DTYPE))
    local, coverage = local_relevance(target, sx, sy)
    assert float(coverage.min()) > 0.99
    # √2 ℓ has mean exp(−b²/4) and variance 2/√3 · exp(−b²/3) − exp(−b²/2) under z ~ N(b, 1).
    expected = math.exp(-offset**2 / 4)
    se = math.sqrt((2 / math.sqrt(3) * math.exp(-offset**2 / 3) - math.exp(-offset**2 / 2)) / draws)
    assert abs(float(source_trust(local, coverage)) - min(expected, 1.0)) < 4 * se + 1e-3


def test_relevance_keeps_what_fits_and_switches_off_what_contradicts_the_target_even_where_it_has_no_data():
    x, y = toy(40, 0)
    fits = relevance(x, y, *toy(20, 1), THETA)
    contradicts = relevance(x, y, *toy(20, 1, shift=1.0), THETA)
    assert float(fits.median()) > 0.5 and float(contradicts.median()) < 1e-3
    # A tuple far from the target's data goes with its source: trusted from one that fits, off from one that does not.
    far_x, far_y = torch.full((1, 2), 30.0, dtype=DTYPE), torch.tensor([[0.5]], dtype=DTYPE)
    fitting = relevance(x, y, torch.cat([toy(20, 1)[0], far_x]), torch.cat([toy(20, 1)[1], far_y]), THETA)
    contradicting = relevance(x, y, torch.cat([toy(20, 1, shift=1.0)[0], far_x]),
                              torch.cat([toy(20, 1, shift=1.0)[1], far_y]), THETA)
    assert float(fitting[-1]) > 0.8 and float(contradicting[-1]) < 0.1


def test_weighted_samples_give_sigma_over_w_at_the_judging_theta():
    w = torch.tensor([[1.0, 0.5], [0.25, MIN_RELEVANCE]], dtype=DTYPE)
    samples = WeightedSamples(torch.zeros(2, 3), torch.zeros(2, 2), w, torch.tensor([0.1, 0.2], dtype=DTYPE))
    torch.testing.assert_close(torch.tensor([0.1, 0.2], dtype=DTYPE) + samples.extra_noise,
                               torch.tensor([0.1, 0.2], dtype=DTYPE) / w)
    assert samples.row() == {SOURCE_SAMPLES: 2.0, RELEVANCE: pytest.approx(float(w.mean())),
                             EFFECTIVE_SAMPLES: pytest.approx(float(w.sum(0).mean()))}


def test_source_tuples_are_thinned_evenly_to_the_maximum(finished_source):
    source = SourceRun.load(finished_source)
    task = source.task
    features = AngleFeatures(task.state_dim, task.angle_dims)
    every = SourceSamples.of(source.dataset, features, range(task.state_dim), 10_000)
    assert len(every.inputs) == len(source.dataset)
    few = SourceSamples.of(source.dataset, features, (1, 3), 5)
    assert few.indices.tolist() == torch.linspace(0, len(source.dataset) - 1, 5).round().long().tolist()
    torch.testing.assert_close(few.targets, every.targets[few.indices][:, [1, 3]], rtol=0, atol=0)


def test_an_output_theta_does_not_hold_keeps_weight_one(finished_source):
    source = SourceRun.load(finished_source)
    features = AngleFeatures(source.task.state_dim, source.task.angle_dims)
    samples = SourceSamples.of(source.dataset, features, range(4), 6)
    weighted = samples.weighted(samples.inputs, samples.targets + 1.0, source.theta.select(torch.tensor([0, 2])),
                                (0, 2))
    assert bool((weighted.weights[:, [1, 3]] == 1).all()) and bool((weighted.weights[:, [0, 2]] < 1).all())
    assert weighted.judged_noise[1] == 0 and weighted.judged_noise[3] == 0


def fit_parts(*overrides: str):
    """The parts of a 2 kg target with ``overrides``."""
    return build(tiny_config(HEAVY, "model.restarts=1", *overrides))


@pytest.mark.parametrize("limit", ["pool", "none"])
def test_the_weighted_fit_is_pooling_at_w_1_and_the_target_alone_as_w_vanishes(finished_source, limit):
    parts = fit_parts()
    source = SourceRun.load(finished_source)
    target = load_checkpoint(latest_checkpoint(finished_source))  # any data of this task serve as the target's
    data = TransitionDataset.from_state(target["dataset"], parts.task.angle_dims)
    data_x, _ = parts.gp_data(data)
    half = len(data_x) // 2
    own = TransitionDataset(parts.task.state_dim, parts.task.action_dim, parts.task.angle_dims)
    own.add_episode(target["dataset"]["states"][0], target["dataset"]["actions"][0])
    own_x, own_y = parts.gp_data(own)
    tuples = SourceSamples.of(source.dataset, parts.features, parts.modelled, 15)
    weight = 1.0 if limit == "pool" else 1e-14
    weights = torch.full_like(tuples.targets, weight)
    samples = WeightedSamples(tuples.inputs, tuples.targets, weights, source.theta.noise_variance.clone())
    gen = torch.Generator().manual_seed(0)
    model = parts.fit_dynamics(own, gen, samples=samples)
    if limit == "pool":
        pooled = DynamicsGP(torch.cat([own_x, tuples.inputs]), torch.cat([own_y, tuples.targets]),
                            model.hyperparameters)
        for got, want in zip(model.predict(data_x[:half]), pooled.predict(data_x[:half]), strict=True):
            torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)
    else:
        alone = DynamicsGP(own_x, own_y, model.hyperparameters)
        for got, want in zip(model.predict(data_x[:half]), alone.predict(data_x[:half]), strict=True):
            torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-8)
        # θ's objective is the target's alone up to a constant: the gap is the same at θ_p and at the target's own fit.
        plain = parts.fit_dynamics(own, torch.Generator().manual_seed(0))

        def gap(theta: GPHyperparameters) -> torch.Tensor:
            alone.hyperparameters, model.hyperparameters = theta, theta
            alone.train()
            model.train()
            with torch.no_grad():
                return model.log_evidence() * len(model.train_x) - alone.log_evidence() * len(own_x)

        torch.testing.assert_close(gap(model.hyperparameters), gap(plain.hyperparameters), rtol=0, atol=1e-6)


def test_samples_are_judged_by_the_target_tuples_own_fit_not_by_a_model_they_helped_fit(finished_source):
    """The judging θ: the target's tuples alone, fitted from θ_s first, then from the last judging θ."""
    cfg = tiny_config(HEAVY, "model.restarts=1", f"transfer.source={finished_source}", "approach=qtl_bayesian",
                      "transfer.samples=relevance", "transfer.max_source_samples=12")
    parts = build(cfg)
    plan = transfer_plan(cfg, parts)
    target = load_checkpoint(latest_checkpoint(finished_source))
    data = TransitionDataset(parts.task.state_dim, parts.task.action_dim, parts.task.angle_dims)
    data.add_episode(target["dataset"]["states"][0], target["dataset"]["actions"][0])
    x, y = parts.gp_data(data)
    starts: list[GPHyperparameters | None] = []

    def judge(start: GPHyperparameters | None) -> DynamicsGP:
        starts.append(start)
        return parts.fit_own(data, torch.Generator().manual_seed(0), start)

    first = plan.source_samples(judge)
    own = parts.fit_own(data, torch.Generator().manual_seed(0), plan.theta_s)
    torch.testing.assert_close(plan.judged.lengthscales, own.hyperparameters.lengthscales, rtol=0, atol=0)
    expected = relevance(x, y, first.inputs, first.targets, own.hyperparameters)
    torch.testing.assert_close(first.weights, expected, rtol=1e-9, atol=1e-300)
    torch.testing.assert_close(first.judged_noise, own.hyperparameters.noise_variance, rtol=0, atol=0)
    plan.source_samples(judge)
    assert starts[0] is plan.theta_s and starts[1] is not None
    torch.testing.assert_close(starts[1].lengthscales, own.hyperparameters.lengthscales, rtol=0, atol=0)


def test_moment_matching_through_a_weighted_model_matches_monte_carlo(finished_source):
    """One step of moment matching through a GP with per-tuple noise against sampling the same GP."""
    source = SourceRun.load(finished_source)
    parts = fit_parts()
    tuples = SourceSamples.of(source.dataset, parts.features, parts.modelled, 20)
    x, y = tuples.inputs[:12], tuples.targets[:12]
    gen = torch.Generator().manual_seed(4)
    extra = 0.05 * torch.rand(12, 4, generator=gen, dtype=DTYPE)
    model = DynamicsGP(x, y, source.theta, extra_noise=extra)
    policy = build(tiny_config(HEAVY)).initial_policy()
    start = Gaussian(source.dataset.tensors(DTYPE)[0][0], 0.01 * torch.eye(4, dtype=DTYPE))
    step, _ = MomentMatching(model, policy, parts.reward, angle_dims=parts.task.angle_dims,
                             include_noise=True).step(start)
    draws = start.sample(20_000, generator=gen)
    with torch.no_grad():
        inputs = torch.cat([parts.features(draws), policy(parts.features(draws))], dim=-1)
        mean, var = model.predict(inputs, include_noise=True)
        nxt = draws + mean + var.sqrt() * torch.randn(mean.shape, generator=gen, dtype=DTYPE)
    err = nxt.std(0) / math.sqrt(len(nxt))
    assert bool(((step.mean - nxt.mean(0)).abs() < 5 * err + 1e-6).all())
    torch.testing.assert_close(step.cov.diagonal(), nxt.var(0), rtol=0.1, atol=1e-6)


def test_samples_need_a_source_and_a_known_mode(tmp_path):
    with pytest.raises(TransferError, match=r"transfer.samples=relevance takes the source's tuples"):
        run(tiny_config("transfer.samples=relevance"), tmp_path / "a")
    with pytest.raises(TransferError, match=r"transfer.samples must be one of"):
        run(tiny_config("transfer.samples=all"), tmp_path / "b")
    with pytest.raises(TransferError, match=r"transfer.max_source_samples must be an integer >= 1"):
        run(tiny_config("transfer.max_source_samples=0"), tmp_path / "c")
    assert not any((tmp_path / d).exists() for d in "abc")


@pytest.mark.parametrize(
    "overrides",
    [
        ["approach=qtl_bayesian"],
        ["rule=free"],
        ["rule=forgetting", "rule.gamma=0.5"],
        ["rule=none", "transfer.hyperparameters=false"],
        ["rule=none", "transfer.hyperparameters=false", "transfer.policy=true"],
    ],
)
def test_sample_transfer_runs_with_every_rule(finished_source, tmp_path, overrides):
    run(tiny_config(f"transfer.source={finished_source}", "transfer.samples=relevance",
                    "transfer.max_source_samples=12", HEAVY, "episodes=2", *overrides), tmp_path)
    rows = read_csv(tmp_path / "metrics.csv")
    assert [float(r[SOURCE_SAMPLES] or 0) for r in rows] == [0.0, 12.0, 12.0]
    for row in rows[1:]:
        assert 0 < float(row[RELEVANCE]) <= 1 and 0 < float(row[EFFECTIVE_SAMPLES]) <= 12
        assert 0.0 <= float(row["compliance"]) <= 1.0


def test_a_resumed_sample_run_equals_an_uninterrupted_one_and_keeps_its_weights(finished_source, tmp_path):
    args = (f"transfer.source={finished_source}", "transfer.samples=relevance", "transfer.max_source_samples=10",
            "approach=qtl_bayesian", HEAVY)
    run(tiny_config("episodes=1", *args), tmp_path / "resumed")
    first = load_checkpoint(latest_checkpoint(tmp_path / "resumed"))["transfer"]["samples"]
    run(tiny_config("episodes=2", *args), tmp_path / "resumed", resume=True)
    run(tiny_config("episodes=2", *args), tmp_path / "straight")
    resumed, straight = ((tmp_path / d / "metrics.csv").read_text() for d in ("resumed", "straight"))
    assert resumed == straight
    # The checkpoint holds the last model's samples and weights exactly as the metrics report them.
    last = load_checkpoint(latest_checkpoint(tmp_path / "straight"))["transfer"]["samples"]
    rows = read_csv(tmp_path / "straight" / "metrics.csv")
    assert float(rows[-1][RELEVANCE]) == float(last["weights"].mean())
    assert float(read_csv(tmp_path / "resumed" / "metrics.csv")[1][RELEVANCE]) == float(first["weights"].mean())
    task = Task.from_config(OmegaConf.to_container(tiny_config(HEAVY).task, resolve=True))
    assert last["inputs"].shape == (10, task.gp_input_dim)


def test_without_samples_the_columns_and_checkpoint_are_unchanged(finished_source, tmp_path):
    run(tiny_config(f"transfer.source={finished_source}", "approach=qtl_bayesian", HEAVY, "episodes=1"), tmp_path)
    assert SOURCE_SAMPLES not in read_csv(tmp_path / "metrics.csv")[0]
    assert "samples" not in load_checkpoint(latest_checkpoint(tmp_path))["transfer"]


@pytest.mark.parametrize(
    "overrides",
    [
        [*PARTICLES_TINY, "propagation.sampling=pathwise"],
        [*PARTICLES_TINY, "propagation.sampling=marginal"],
        [*TINY, "model=sparse", "model.inducing=10"],
    ],
    ids=["pathwise", "marginal", "sparse"],
)
def test_sample_transfer_runs_with_particles_and_the_sparse_gp(finished_source, tmp_path, overrides):
    run(train_config(*overrides, f"transfer.source={finished_source}", "transfer.samples=relevance",
                     "transfer.max_source_samples=12", "rule=bayesian", HEAVY, "episodes=1"), tmp_path)
    rows = read_csv(tmp_path / "metrics.csv")
    assert float(rows[1][SOURCE_SAMPLES]) == 12 and math.isfinite(float(rows[1]["predicted_return"]))
