"""The state dimensions a dynamics GP's outputs are: recorded, checked, saved, and naming θ's keys."""

from __future__ import annotations

import pytest
import torch

from qtl.models import DynamicsGP, ExactFit, GPHyperparameters, PreviousFit, SparseDynamicsGP
from qtl.models.fitting import _warm_from

DTYPE = torch.float64
OUTPUTS = (1, 3)


def data(n: int = 20, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Inputs `n x 3` and two smooth targets `n x 2`."""
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 3, generator=gen, dtype=DTYPE)
    return x, torch.stack([x[:, 0].sin(), x[:, 1] * x[:, 2]], dim=-1) + 0.01 * torch.randn(n, 2, generator=gen,
                                                                                           dtype=DTYPE)


@pytest.mark.parametrize("cls", [DynamicsGP, SparseDynamicsGP])
def test_a_checkpoint_round_trip_keeps_the_outputs_and_the_state_dimension(cls, tmp_path):
    x, y = data()
    model = cls(x, y, outputs=OUTPUTS, state_dim=5)
    model.save(tmp_path / "gp.pt")
    loaded = cls.load(tmp_path / "gp.pt")
    assert loaded.outputs == OUTPUTS and loaded.state_dim == 5
    torch.testing.assert_close(loaded.hyperparameters.natural(), model.hyperparameters.natural(), rtol=0, atol=0)


def test_a_state_without_outputs_models_all_of_an_e_dimensional_state():
    x, y = data()
    state = DynamicsGP(x, y).state()
    del state["outputs"], state["state_dim"]  # as written before models held them
    old = DynamicsGP.from_state(state)
    assert old.outputs == (0, 1) and old.state_dim == 2


@pytest.mark.parametrize(("outputs", "state_dim"), [((1,), None), ((1, 1), None), ((-1, 2), None), ((1, 3), 3)])
def test_outputs_that_are_not_one_distinct_state_dimension_each_are_refused(outputs, state_dim):
    x, y = data()
    with pytest.raises(ValueError, match="distinct state dimensions"):
        DynamicsGP(x, y, outputs=outputs, state_dim=state_dim)


def test_the_state_dimension_defaults_to_the_largest_output_plus_one():
    x, y = data()
    assert DynamicsGP(x, y, outputs=OUTPUTS).state_dim == 4


def test_a_fit_records_its_outputs_and_the_previous_fit_carries_them():
    x, y = data()
    model = ExactFit(restarts=1, max_iter=3).fit(x, y, outputs=OUTPUTS, state_dim=4)
    assert model.outputs == OUTPUTS and model.hyperparameters.num_outputs == 2
    previous = PreviousFit.of(model)
    assert previous.modelled == OUTPUTS
    assert PreviousFit.from_state_dict(previous.state_dict()).modelled == OUTPUTS
    # Warm fits start only from a fit of the same outputs; one recorded without them is of 0..E−1.
    assert _warm_from(previous, model) is not None
    other = ExactFit(restarts=1, max_iter=3).fit(x, y, outputs=(0, 2), state_dim=4)
    assert _warm_from(previous, other) is None
    legacy = PreviousFit(previous.theta, previous.objective, previous.num_points)
    assert legacy.modelled == (0, 1) and _warm_from(legacy, model) is None


def test_theta_keys_name_the_state_dimensions_and_read_back():
    theta = GPHyperparameters(torch.tensor([[1.0, 2.0], [3.0, 4.0]], dtype=DTYPE), torch.tensor([0.5, 0.6]),
                              torch.tensor([0.01, 0.02]))
    flat = theta.as_dict(OUTPUTS)
    assert list(flat)[:4] == ["out1/lengthscale/in0", "out1/lengthscale/in1", "out1/signal_variance",
                              "out1/noise_variance"]
    assert "out3/noise_variance" in flat and not any(k.startswith("out0/") for k in flat)
    back = GPHyperparameters.from_dict({f"theta/{k}": v for k, v in flat.items()}, "theta/")
    torch.testing.assert_close(back.natural(), theta.natural().to(DTYPE), rtol=0, atol=1e-7)
    assert list(theta.as_dict()) == GPHyperparameters.keys(2, 2)  # by default 0..E−1, as before
    with pytest.raises(ValueError, match="name 1 outputs, θ has 2"):
        theta.as_dict((1,))
