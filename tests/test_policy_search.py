"""Policy search: finds the maximum, keeps the best ψ across restarts, survives invalid ψ."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from qtl.errors import NonFiniteObjective
from qtl.policy_search import AdamSearch, LBFGSSearch


class Point(nn.Module):
    def __init__(self, start: list[float]) -> None:
        super().__init__()
        self.x = nn.Parameter(torch.tensor(start, dtype=torch.float64))


def bowl(point: Point) -> torch.Tensor:
    """A concave objective with its maximum 1 at (1, −2)."""
    return 1.0 - ((point.x - torch.tensor([1.0, -2.0], dtype=torch.float64)) ** 2).sum()


@pytest.mark.parametrize("search", [LBFGSSearch(max_iter=50, restarts=2), AdamSearch(steps=400, lr=0.05)])
def test_finds_the_maximum_and_leaves_it_in_the_policy(search):
    point = Point([0.0, 0.0])
    result = search(point, lambda: bowl(point), generator=torch.Generator().manual_seed(0))
    assert result.value == pytest.approx(1.0, abs=1e-4)
    torch.testing.assert_close(point.x.detach(), torch.tensor([1.0, -2.0], dtype=torch.float64), atol=1e-2, rtol=0)
    assert result.evaluations > 0 and len(result.run_values) == search.restarts


def test_invalid_region_stops_the_run_but_keeps_the_best_point_seen():
    point = Point([0.0, 0.0])

    def objective() -> torch.Tensor:
        if point.x[0] > 0.5:  # the propagation "breaks down" past x0 = 0.5
            raise torch.linalg.LinAlgError("not positive-definite")
        return bowl(point)

    result = LBFGSSearch(max_iter=50, restarts=1)(point, objective)
    assert math.isfinite(result.value) and point.x[0] <= 0.5
    assert result.evaluations >= 2  # the failed evaluation counts too
    assert result.value == pytest.approx(float(bowl(point)))


def test_nan_everywhere_is_reported():
    point = Point([0.0, 0.0])
    with pytest.raises(NonFiniteObjective, match="no policy search run"):
        LBFGSSearch(max_iter=5, restarts=2)(point, lambda: point.x.sum() * math.nan)


def test_bad_settings_are_named():
    with pytest.raises(ValueError, match="restarts must be >= 1"):
        LBFGSSearch(restarts=0)
    with pytest.raises(ValueError, match="max_iter must be >= 1"):
        LBFGSSearch(max_iter=0)
    with pytest.raises(ValueError, match="steps must be >= 1 and lr > 0"):
        AdamSearch(lr=0.0)
