"""Warm-started evidence maximisation (``model.warm_start``): as good as the cold fit, restarts only where short."""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from qtl.models import DynamicsGP, ExactFit, GPHyperparameters, PreviousFit, SparseDynamicsGP, SparseFit
from qtl.models.gp_evidence import WARM_RESTART_TOLERANCE

N, EPISODE, D, E = 40, 8, 3, 2
MAX_ITER = 20


@pytest.fixture(scope="module")
def data() -> tuple[Tensor, Tensor]:
    """Inputs `N x D` and targets `N x E` of a smooth function with noise."""
    gen = torch.Generator().manual_seed(1)
    x = torch.rand(N, D, generator=gen, dtype=torch.float64) * 4 - 2
    w = torch.randn(D, E, generator=gen, dtype=torch.float64)
    return x, torch.sin(x @ w / 2) + 0.05 * torch.randn(N, E, generator=gen, dtype=torch.float64)


@pytest.fixture(scope="module")
def previous(data) -> PreviousFit:
    """θ_p of the data less its last episode, as the previous episode hands it over."""
    x, y = data
    model = DynamicsGP(x[:-EPISODE], y[:-EPISODE])
    model.fit(restarts=1, max_iter=MAX_ITER)
    return PreviousFit.of(model)


def generator() -> torch.Generator:
    return torch.Generator().manual_seed(0)


class RunCounter:
    """Counts the L-BFGS runs of every DynamicsGP and the outputs each one fitted."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.outputs: list[int] = []
        one_run = DynamicsGP._optimise

        def counted(model: DynamicsGP, max_iter: int) -> Tensor:
            self.outputs.append(model.num_outputs)
            return one_run(model, max_iter)

        monkeypatch.setattr(DynamicsGP, "_optimise", counted)


def assert_same_theta(a: GPHyperparameters, b: GPHyperparameters) -> None:
    torch.testing.assert_close(a.log(), b.log(), rtol=0, atol=0)


def test_the_warm_fit_reaches_the_cold_fits_objective(data, previous):
    x, y = data
    cold = DynamicsGP(x, y).fit(restarts=3, max_iter=MAX_ITER, generator=generator())
    warm = DynamicsGP(x, y).fit_warm(previous.theta, previous.objective, restarts=3, max_iter=MAX_ITER,
                                     generator=generator())
    assert (warm >= cold - 1e-3).all(), (warm, cold)


def test_no_output_short_runs_no_restart(data, previous, monkeypatch):
    counter = RunCounter(monkeypatch)
    model = DynamicsGP(*data)
    value = model.fit_warm(previous.theta, previous.objective, restarts=3, max_iter=MAX_ITER, generator=generator())
    assert counter.outputs == [E]  # the one warm run, over both outputs
    assert (value >= previous.objective - WARM_RESTART_TOLERANCE).all()
    torch.testing.assert_close(model.fit_objective, value, rtol=0, atol=0)


def test_restarts_run_only_for_the_short_output(data, previous, monkeypatch):
    warm_only = DynamicsGP(*data)
    warm_only.fit_warm(previous.theta, torch.full((E,), -math.inf), max_iter=MAX_ITER)
    counter = RunCounter(monkeypatch)
    model = DynamicsGP(*data)
    reference = torch.tensor([-math.inf, math.inf], dtype=torch.float64)  # output 1 can never be good enough
    model.fit_warm(previous.theta, reference, restarts=3, max_iter=MAX_ITER, generator=generator())
    assert counter.outputs == [E, 1, 1, 1]  # the warm run, then 3 cold runs of output 1 alone
    theta, alone = model.hyperparameters, warm_only.hyperparameters
    torch.testing.assert_close(theta.lengthscales[0], alone.lengthscales[0], rtol=0, atol=0)  # output 0 untouched
    cold = DynamicsGP(data[0], data[1][:, 1:])
    cold_value = cold.fit(restarts=3, max_iter=MAX_ITER, generator=generator())
    best = max(float(cold_value[0]), float(warm_only.fit_objective[1]))
    assert float(model.fit_objective[1]) == pytest.approx(best, abs=1e-9)  # output 1: the better of warm, cold


def test_one_outputs_objective_is_the_same_in_a_model_of_it_alone(data):
    model, alone = DynamicsGP(*data), DynamicsGP(data[0], data[1][:, 1:])
    model.train()
    alone.train()
    with torch.no_grad():
        torch.testing.assert_close(model.log_evidence()[1:], alone.log_evidence(), rtol=1e-12, atol=0)


def test_an_unusable_previous_theta_falls_back_to_the_cold_fit(data):
    x, y = data
    wrong = GPHyperparameters(torch.ones(E + 1, D), torch.ones(E + 1), torch.ones(E + 1) * 0.1)  # E + 1 outputs
    model = DynamicsGP(x, y)
    model.fit_warm(wrong.to(torch.float64), torch.zeros(E, dtype=torch.float64), restarts=2, max_iter=MAX_ITER,
                   generator=generator())
    cold = DynamicsGP(x, y)
    cold.fit(restarts=2, max_iter=MAX_ITER, generator=generator())
    assert_same_theta(model.hyperparameters, cold.hyperparameters)


def test_warm_start_off_ignores_the_previous_fit_and_on_uses_it(data, previous):
    x, y = data
    plain = ExactFit(restarts=2, max_iter=MAX_ITER).fit(x, y, generator=generator())
    ignored = ExactFit(restarts=2, max_iter=MAX_ITER).fit(x, y, generator=generator(), previous=previous)
    assert_same_theta(ignored.hyperparameters, plain.hyperparameters)
    warm = ExactFit(restarts=2, max_iter=MAX_ITER, warm_start=True).fit(x, y, generator=generator(), previous=previous)
    direct = DynamicsGP(x, y)
    direct.fit_warm(previous.theta, previous.objective, restarts=2, max_iter=MAX_ITER, generator=generator())
    assert_same_theta(warm.hyperparameters, direct.hyperparameters)
    first = ExactFit(restarts=2, max_iter=MAX_ITER, warm_start=True).fit(x, y, generator=generator())
    assert_same_theta(first.hyperparameters, plain.hyperparameters)  # no previous fit: the cold fit


def test_a_previous_fit_of_less_than_half_the_data_is_not_started_from(data, previous):
    x, y = data
    cold = ExactFit(restarts=2, max_iter=MAX_ITER).fit(x, y, generator=generator())
    few = PreviousFit(previous.theta, previous.objective, num_points=N // 2 - 1)
    assert previous.speaks_for(N) and not few.speaks_for(N)
    fitted = ExactFit(restarts=2, max_iter=MAX_ITER, warm_start=True).fit(x, y, generator=generator(), previous=few)
    assert_same_theta(fitted.hyperparameters, cold.hyperparameters)


def test_the_sparse_warm_fit_starts_from_the_previous_inducing_inputs(data, monkeypatch):
    x, y = data
    before = SparseFit(restarts=1, max_iter=MAX_ITER, inducing=8).fit(x[:-EPISODE], y[:-EPISODE],
                                                                     generator=generator())
    previous = PreviousFit.of(before)
    assert previous.inducing is not None and previous.inducing.shape == (8, D)
    counter = RunCounter(monkeypatch)
    seen: list[Tensor] = []
    one_run = DynamicsGP._optimise  # the counter's wrapper

    def spy(model: DynamicsGP, max_iter: int) -> Tensor:
        seen.append(model.inducing_points.clone())
        return one_run(model, max_iter)

    monkeypatch.setattr(SparseDynamicsGP, "_optimise", spy, raising=False)
    warm = SparseFit(restarts=2, max_iter=MAX_ITER, inducing=8, warm_start=True).fit(
        x, y, generator=generator(), previous=previous)
    assert counter.outputs == [E]  # the warm bound is not short: no restart
    torch.testing.assert_close(seen[0], previous.inducing, rtol=0, atol=0)
    cold = SparseFit(restarts=2, max_iter=MAX_ITER, inducing=8).fit(x, y, generator=generator())
    assert float(warm.fit_objective.sum()) >= float(cold.fit_objective.sum()) - 1e-2


def test_a_short_sparse_warm_fit_runs_the_cold_restarts_and_keeps_the_better(data, monkeypatch):
    x, y = data
    before = SparseFit(restarts=1, max_iter=MAX_ITER, inducing=8).fit(x[:-EPISODE], y[:-EPISODE],
                                                                     generator=generator())
    previous = PreviousFit.of(before)
    counter = RunCounter(monkeypatch)
    model = SparseDynamicsGP(x, y, num_inducing=8, generator=generator())
    value = model.fit_warm(previous.theta, torch.full((E,), math.inf, dtype=torch.float64),
                           inducing=previous.inducing, restarts=2, max_iter=MAX_ITER, generator=generator())
    assert counter.outputs == [E, E, E]  # warm, then the 2 cold restarts (Z is shared: all outputs)
    assert torch.isfinite(value).all()
    torch.testing.assert_close(model.fit_objective, value, rtol=0, atol=0)


def test_previous_fit_round_trips_through_a_checkpoint(tmp_path, previous):
    path = tmp_path / "previous.pt"
    torch.save(previous.state_dict(), path)
    loaded = PreviousFit.from_state_dict(torch.load(path, weights_only=True))
    assert_same_theta(loaded.theta, previous.theta)
    torch.testing.assert_close(loaded.objective, previous.objective, rtol=0, atol=0)
    assert loaded.num_points == N - EPISODE and loaded.inducing is None


def test_a_run_checkpoint_gives_its_previous_fit_or_none_when_it_predates_warm_starts(previous):
    loaded = PreviousFit.of_checkpoint({"episode": 3, "previous_fit": previous.state_dict()})
    assert loaded is not None and loaded.num_points == previous.num_points
    torch.testing.assert_close(loaded.objective, previous.objective, rtol=0, atol=0)
    assert PreviousFit.of_checkpoint({"episode": 3, "previous_fit": None}) is None
    assert PreviousFit.of_checkpoint({"episode": 3}) is None  # a checkpoint made before model.warm_start


def test_an_unfitted_model_has_no_previous_fit(data):
    with pytest.raises(ValueError, match="has not been fitted"):
        PreviousFit.of(DynamicsGP(*data))
