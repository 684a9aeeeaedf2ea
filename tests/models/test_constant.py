"""Constant outputs, detected at each fit: neither a crash nor a GP, but a deterministic Δ (the data's mean)."""

from __future__ import annotations

import logging

import pytest
import torch

from qtl import health
from qtl.models import AutoFit, DynamicsGP, ExactFit, PreviousFit, SparseFit
from qtl.models.constant import CONSTANT_DELTA_ATOL, CONSTANT_DELTA_RTOL, constant_columns, split_outputs

DTYPE = torch.float64


def data(n: int = 24, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Inputs `n x 3` and four targets `n x 4`: two smooth ones, a zero Δ (a contact force), a fixed step (a clock)."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 3, generator=gen, dtype=DTYPE)
    smooth = torch.stack([x[:, 0].sin(), x[:, 1] * x[:, 2]], dim=-1) + 0.01 * torch.randn(n, 2, generator=gen,
                                                                                          dtype=DTYPE)
    return x, torch.cat([smooth, torch.zeros(n, 1, dtype=DTYPE), torch.full((n, 1), 0.05, dtype=DTYPE)], dim=-1)


def test_the_criterion_is_the_stated_tolerance():
    column = torch.zeros(50, 1, dtype=DTYPE)
    spread = torch.linspace(-1.0, 1.0, 50, dtype=DTYPE)[:, None]
    spread = spread / spread.std(correction=0)  # unit standard deviation
    at, above = CONSTANT_DELTA_ATOL, 1.01 * CONSTANT_DELTA_ATOL
    assert constant_columns(column + at * spread).tolist() == [True]
    assert constant_columns(column + above * spread).tolist() == [False]
    clock = 2.0 + 0.99 * CONSTANT_DELTA_RTOL * 2.0 * spread  # relative to |mean Δ| (float rounding of a clock)
    assert constant_columns(clock).tolist() == [True]
    assert constant_columns(2.0 + 1e-4 * spread).tolist() == [False]


def test_split_names_the_state_dimensions_and_takes_the_data_mean():
    _, y = data()
    split = split_outputs(y, (1, 3, 4, 6))
    assert split.varying == [0, 1] and split.outputs == (1, 3) and split.constant_outputs == (4, 6)
    torch.testing.assert_close(split.constant_delta, torch.tensor([0.0, 0.05], dtype=DTYPE), rtol=0, atol=1e-17)
    with pytest.raises(ValueError, match=r"every modelled output \[0\] is constant"):
        split_outputs(torch.zeros(5, 1, dtype=DTYPE))


@pytest.mark.parametrize("fitter", [ExactFit(restarts=1, max_iter=3), SparseFit(restarts=1, max_iter=3, inducing=8),
                                    AutoFit(restarts=1, max_iter=3)], ids=["exact", "sparse", "auto"])
def test_a_fit_models_constant_outputs_as_deterministic(fitter, caplog):
    x, y = data()
    health.take()
    with caplog.at_level(logging.INFO, logger="qtl.models.fitting"):
        model = fitter.fit(x, y, state_dim=4)
    assert model.outputs == (0, 1) and model.constant_outputs == (2, 3) and model.num_outputs == 2
    torch.testing.assert_close(model.constant_delta, torch.tensor([0.0, 0.05], dtype=DTYPE), rtol=0, atol=1e-17)
    assert health.take()[health.CONSTANT_OUTPUTS] == 2
    assert [r.message for r in caplog.records if "deterministic" in r.message] == [
        "outputs [2, 3]: Δ constant in the data (std <= 1e-09 + 1e-06 |mean|), modelled as deterministic "
        "(Δ = [0.0, 0.05], no variance); the GP learns outputs [0, 1]"]
    # The next fit, told of this one, counts them again but logs nothing new.
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="qtl.models.fitting"):
        again = fitter.fit(x, y, state_dim=4, previous=PreviousFit.of(model))
    assert again.constant_outputs == (2, 3) and health.take()[health.CONSTANT_OUTPUTS] == 2
    assert not [r for r in caplog.records if "deterministic" in r.message]


def test_a_start_theta_of_every_modelled_output_gives_the_gp_its_rows():
    x, y = data()
    first = ExactFit(restarts=1, max_iter=3).fit(x, y[:, :2])
    theta = first.hyperparameters
    four = type(theta)(torch.cat([theta.lengthscales, theta.lengthscales]), torch.cat([theta.signal_variance] * 2),
                       torch.cat([theta.noise_variance] * 2))
    model = ExactFit(restarts=1, max_iter=1).fit(x, y, start=four, state_dim=4)
    assert model.hyperparameters.num_outputs == 2


def test_a_checkpoint_keeps_the_constant_outputs(tmp_path):
    x, y = data()
    model = ExactFit(restarts=1, max_iter=3).fit(x, y, state_dim=4)
    model.save(tmp_path / "gp.pt")
    loaded = DynamicsGP.load(tmp_path / "gp.pt")
    assert loaded.constant_outputs == (2, 3) and loaded.outputs == (0, 1)
    torch.testing.assert_close(loaded.constant_delta, model.constant_delta, rtol=0, atol=0)
    cache = loaded.posterior_cache()
    assert cache.constant_outputs == (2, 3) and cache.state_dim == 4
    previous = PreviousFit.from_state_dict(PreviousFit.of(model).state_dict())
    assert previous.constant_outputs == (2, 3)


def test_a_tiny_but_varying_output_no_longer_falls_below_the_noise_floor():
    # var(Δ) / 100 below the floor 1e-10 made the heuristic θ refuse itself: the heuristic noise is now the floor.
    x, y = data()
    tiny = 1e-7 * y[:, :1]
    model = DynamicsGP(x, tiny)
    assert float(model.hyperparameters.noise_variance) >= 1e-10
    assert not constant_columns(tiny).any()
