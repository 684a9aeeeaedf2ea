"""The generator L-BFGS evaluates exactly the points ``torch.optim.LBFGS(line_search_fn="strong_wolfe")`` does."""

from __future__ import annotations

import itertools
from collections.abc import Callable

import pytest
import torch
from torch import Tensor

import qtl.lbfgs
from qtl.lbfgs import LBFGSOptions, lbfgs, minimise

Objective = Callable[[Tensor], Tensor]


def rosenbrock(x: Tensor) -> Tensor:
    """Σ_i 100 (x_{i+1} − x_i²)² + (1 − x_i)²: a curved valley, minimum 0 at (1, …, 1)."""
    return (100 * (x[1:] - x[:-1].square()).square() + (1 - x[:-1]).square()).sum()


def quadratic(dim: int, seed: int, scale: float = 1.0) -> Objective:
    """½ xᵀ A x − bᵀ x with a random, well-conditioned A ≻ 0 (``scale`` shrinks the gradients)."""
    gen = torch.Generator().manual_seed(seed)
    m = torch.randn(dim, dim, generator=gen, dtype=torch.float64)
    a = scale * (m @ m.T / dim + 0.5 * torch.eye(dim, dtype=torch.float64))
    b = scale * torch.randn(dim, generator=gen, dtype=torch.float64)
    return lambda x: 0.5 * x @ a.to(x.dtype) @ x - b.to(x.dtype) @ x


def log_cosh(x: Tensor) -> Tensor:
    """Flat far out (gradients near ±1 per entry): steps must be extrapolated to reach the bottom."""
    return torch.log(torch.cosh(x - 3.0)).sum()


def kinked(x: Tensor) -> Tensor:
    """5 ‖x − 0.3‖₁ + ‖x + 1‖²: a kink at the minimum, where the cubic fits fail and the bracket shrinks to nothing."""
    return 5 * (x - 0.3).abs().sum() + (x + 1).square().sum()


def cliff(x: Tensor) -> Tensor:
    """A gentle downhill slope that turns into a steep wall past 1: trials land by the bracket's ends."""
    wall = torch.where(x > 1, 10 * (x - 1).square(), torch.zeros_like(x))
    return (wall - 0.5 * x + 0.01 * x.square()).sum()


def double_well(x: Tensor) -> Tensor:
    """Σ (x_i² − 1)²: minima at ±1, stops on a small change of the loss."""
    return (x.square() - 1).square().sum()


PROBLEMS: dict[str, tuple[Objective, list[float]]] = {
    "rosenbrock-5d": (rosenbrock, [-1.2, 1.0, -1.2, 1.0, 0.5]),
    "quadratic-10d": (quadratic(10, seed=3), [0.0] * 10),
    "small-quadratic-4d": (quadratic(4, seed=5, scale=1e-2), [0.3, -0.2, 0.1, 0.4]),  # first step 1, a float
    "log-cosh-3d": (log_cosh, [-4.0, -6.0, -5.0]),
    "kinked-3d": (kinked, [2.0, -2.0, 0.5]),
    "cliff-2d": (cliff, [-2.0, 0.0]),
    "double-well-3d": (double_well, [0.1, -0.3, 2.0]),
    "stationary-2d": (log_cosh, [3.0, 3.0]),  # the gradient is 0 at the start: one evaluation
}


def torch_run(f: Objective, start: list[float], split: int, options: LBFGSOptions,
              dtype: torch.dtype) -> tuple[list[Tensor], Tensor]:
    """Points torch's LBFGS evaluates (ψ split into two parameters at ``split``) and where it leaves ψ."""
    full = torch.tensor(start, dtype=dtype)
    params = [torch.nn.Parameter(full[:split].clone()), torch.nn.Parameter(full[split:].clone())]
    optimiser = torch.optim.LBFGS(params, lr=options.lr, max_iter=options.max_iter, max_eval=options.max_eval,
                                  tolerance_grad=options.tolerance_grad, tolerance_change=options.tolerance_change,
                                  history_size=options.history_size, line_search_fn="strong_wolfe")
    points = []

    def closure() -> Tensor:
        optimiser.zero_grad()
        x = torch.cat(params)
        points.append(x.detach().clone())
        loss = f(x)
        loss.backward()
        return loss

    optimiser.step(closure)
    return points, torch.cat(params).detach()


def generator_run(f: Objective, start: list[float], options: LBFGSOptions,
                  dtype: torch.dtype) -> tuple[list[Tensor], Tensor]:
    """Points :func:`qtl.lbfgs.minimise` evaluates on the flat problem, and its final x."""
    points = []

    def evaluate(point: Tensor) -> tuple[float, Tensor]:
        points.append(point.clone())
        x = point.clone().requires_grad_(True)
        loss = f(x)
        (grad,) = torch.autograd.grad(loss, x)
        return float(loss.detach()), grad

    final = minimise(evaluate, torch.tensor(start, dtype=dtype), options)
    return points, final


CASES = [(name, max_iter, torch.float64) for name, max_iter in itertools.product(PROBLEMS, [1, 3, 25, 100])]
CASES += [("rosenbrock-5d", 100, torch.float32), ("kinked-3d", 100, torch.float32)]


@pytest.mark.parametrize(("problem", "max_iter", "dtype"), CASES)
def test_the_same_points_as_torch_bit_for_bit(problem, max_iter, dtype):
    """The evaluated points, their number and the final x equal torch's exactly (max_eval = max_iter, as searches)."""
    f, start = PROBLEMS[problem]
    options = LBFGSOptions(max_iter=max_iter, max_eval=max_iter)
    want, want_final = torch_run(f, start, 2, options, dtype)
    got, got_final = generator_run(f, start, options, dtype)
    assert len(got) == len(want)
    for i, (g, w) in enumerate(zip(got, want, strict=True)):
        assert torch.equal(g, w), f"evaluation {i}: {g.tolist()} vs torch {w.tolist()}"
    assert torch.equal(got_final, want_final) and got_final.dtype == dtype


@pytest.mark.parametrize("options", [LBFGSOptions(max_iter=40), LBFGSOptions(max_iter=30, history_size=2),
                                     LBFGSOptions(max_iter=60, max_eval=70, tolerance_grad=1e-4,
                                                  tolerance_change=1e-6, lr=0.5)])
def test_other_options_follow_torch_too(options):
    """torch's default max_eval (max_iter · 5/4), a short memory, looser tolerances and lr < 1."""
    f, start = PROBLEMS["rosenbrock-5d"]
    want, want_final = torch_run(f, start, 3, options, torch.float64)
    got, got_final = generator_run(f, start, options, torch.float64)
    assert len(got) == len(want) and all(torch.equal(g, w) for g, w in zip(got, want, strict=True))
    assert torch.equal(got_final, want_final)


def test_the_problems_exercise_both_phases_of_the_line_search(monkeypatch):
    """The cubic step is bounded while bracketing (extrapolation) and unbounded while zooming: both happen."""
    calls = {}
    cubic = qtl.lbfgs._cubic_minimiser

    def counting(*args, bounds=None):
        calls[problem, "extrapolate" if bounds is not None else "zoom"] = True
        return cubic(*args, bounds=bounds)

    monkeypatch.setattr(qtl.lbfgs, "_cubic_minimiser", counting)
    for problem, (f, start) in PROBLEMS.items():  # noqa: B007 (read by counting)
        generator_run(f, start, LBFGSOptions(max_iter=100, max_eval=100), torch.float64)
    assert {("rosenbrock-5d", "zoom"), ("kinked-3d", "zoom"), ("cliff-2d", "zoom"), ("log-cosh-3d", "extrapolate"),
            ("double-well-3d", "extrapolate")} <= set(calls)
    assert not any(problem == "stationary-2d" for problem, _ in calls)


def test_converges_and_stops_early_on_a_quadratic():
    """On a convex quadratic L-BFGS gets close to the minimiser and stops (gᵀd ≈ 0) well within its budget."""
    dim = 10
    f = quadratic(dim, seed=3)
    points, final = generator_run(f, [0.0] * dim, LBFGSOptions(max_iter=100, max_eval=100), torch.float64)
    x = final.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(f(x), x)
    assert grad.abs().max() <= 1e-4 and len(points) < 40


def test_the_generator_protocol():
    """It first yields a copy of the start, and returns at once when the start is stationary."""
    start = torch.tensor([1.0, 2.0], dtype=torch.float64)
    run = lbfgs(start, LBFGSOptions(max_iter=5))
    first = next(run)
    assert torch.equal(first, start) and first is not start
    with pytest.raises(StopIteration) as stop:
        run.send((0.0, torch.zeros(2, dtype=torch.float64)))
    assert torch.equal(stop.value.value, start)


def test_eval_budget_defaults_to_torchs():
    assert LBFGSOptions(max_iter=20).eval_budget == 25 and LBFGSOptions(max_iter=8, max_eval=3).eval_budget == 3
