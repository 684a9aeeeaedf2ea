"""The ``model`` group's fitters: which GP each option fits, with the same numbers as the GP's own fit."""

from __future__ import annotations

import itertools
import logging

import pytest
import torch

from qtl.models import AutoFit, DynamicsGP, ExactFit, SparseDynamicsGP, SparseFit, log_evidence

N = 30


@pytest.fixture(scope="module")
def pairs(gp_factory) -> tuple[torch.Tensor, torch.Tensor]:
    """Training inputs `N x 4` and targets `N x 2` of a toy dynamics."""
    gp = gp_factory(N, 2, 1, angle_dims=(1,))
    return gp.train_x, gp.train_y


def generator() -> torch.Generator:
    return torch.Generator().manual_seed(0)


def assert_same_theta(a: DynamicsGP, b: DynamicsGP) -> None:
    for name in ("lengthscales", "signal_variance", "noise_variance"):
        torch.testing.assert_close(getattr(a.hyperparameters, name), getattr(b.hyperparameters, name), rtol=0, atol=0)


def test_exact_fit_is_the_gps_own_evidence_maximisation(pairs):
    inputs, targets = pairs
    model = ExactFit(restarts=2, max_iter=5).fit(inputs, targets, generator=generator())
    reference = DynamicsGP(inputs, targets)
    reference.fit(restarts=2, max_iter=5, generator=generator())
    assert type(model) is DynamicsGP and model.train_x.dtype == inputs.dtype
    assert_same_theta(model, reference)
    assert log_evidence(model) > log_evidence(DynamicsGP(inputs, targets))  # the fit improved on the heuristic θ


def test_sparse_fit_uses_at_most_its_inducing_inputs(pairs):
    inputs, targets = pairs
    for inducing, expected in ((10, 10), (100, N)):
        model = SparseFit(restarts=1, max_iter=3, inducing=inducing).fit(inputs, targets, generator=generator())
        assert isinstance(model, SparseDynamicsGP) and model.inducing_points.shape == (expected, inputs.shape[1])


@pytest.mark.parametrize(("sparse_above", "sparse"), [(None, False), (N, False), (N - 1, True), (0, True)])
def test_auto_fit_switches_above_the_threshold_with_the_chosen_options_numbers(pairs, caplog, sparse_above, sparse):
    inputs, targets = pairs
    with caplog.at_level(logging.INFO, logger="qtl.models.fitting"):
        model = AutoFit(restarts=1, max_iter=3, sparse_above=sparse_above, inducing=8).fit(
            inputs, targets, generator=generator())
    chosen = SparseFit(1, 3, 8) if sparse else ExactFit(1, 3)
    assert type(model) is type(chosen.fit(inputs, targets, generator=generator()))
    assert_same_theta(model, chosen.fit(inputs, targets, generator=generator()))
    message = f"{N} tuples > model.sparse_above={sparse_above}: the sparse GP, 8 inducing inputs"
    assert (message in caplog.text) == sparse


def test_fit_starts_from_the_given_theta(pairs):
    inputs, targets = pairs
    start = ExactFit(restarts=1, max_iter=5).fit(inputs, targets, generator=generator()).hyperparameters
    again = ExactFit(restarts=1, max_iter=1).fit(inputs, targets, start=start, generator=generator())
    heuristic = ExactFit(restarts=1, max_iter=1).fit(inputs, targets, generator=generator())
    gap = (again.hyperparameters.lengthscales - start.lengthscales).abs().max()
    assert gap < (heuristic.hyperparameters.lengthscales - start.lengthscales).abs().max()


def test_the_defaults_are_the_published_ones():  # restarts 3, 100 iterations, sparse above 1000 tuples, m = 300
    assert ExactFit() == ExactFit(restarts=3, max_iter=100)
    assert AutoFit() == AutoFit(restarts=3, max_iter=100, sparse_above=1000, inducing=300)
    assert SparseFit().inducing == AutoFit().inducing


@pytest.mark.parametrize(("kind", "bad"), list(itertools.product(
    (ExactFit, SparseFit, AutoFit), ({"restarts": 0}, {"max_iter": 0}))))
def test_a_bad_budget_fails_when_the_option_is_made(kind, bad):
    with pytest.raises(ValueError, match=rf"model\.{next(iter(bad))} must be >= 1"):
        kind(**bad)


def test_bad_sparse_settings_fail_when_the_option_is_made():
    with pytest.raises(ValueError, match=r"model\.inducing must be >= 1"):
        SparseFit(inducing=0)
    with pytest.raises(ValueError, match=r"model\.sparse_above must be >= 0 or null"):
        AutoFit(sparse_above=-1)
    for kind in (SparseFit, AutoFit):
        with pytest.raises(ValueError, match=r"model\.inducing_jitter must be >= 0"):
            kind(inducing_jitter=-1e-6)


def test_the_sparse_fits_pass_their_jitter_to_the_model(gp_factory):
    gp = gp_factory(30, 2, 1, seed=3)
    model = SparseFit(restarts=1, max_iter=2, inducing=8, inducing_jitter=1e-3).fit(
        gp.train_x, gp.train_y, generator=torch.Generator().manual_seed(0))
    assert model.jitter == 1e-3
    model = AutoFit(restarts=1, max_iter=2, sparse_above=10, inducing=8, inducing_jitter=0.0).fit(
        gp.train_x, gp.train_y, generator=torch.Generator().manual_seed(0))
    assert model.jitter == 0.0


def test_log_evidence_is_the_mean_over_outputs_and_leaves_the_model_in_eval_mode(pairs):
    model = DynamicsGP(*pairs)
    model.train()
    with torch.no_grad():
        expected = float(model.log_evidence().mean())
    model.eval()
    assert log_evidence(model) == expected and not model.training
