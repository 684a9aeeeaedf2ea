"""L-BFGS with a strong-Wolfe line search, written as a generator that asks its caller for evaluations.

:func:`lbfgs` is the algorithm of ``torch.optim.LBFGS(..., line_search_fn="strong_wolfe").step``
(Nocedal & Wright, Algorithms 7.4 and 3.5-3.6, in the form minFunc and torch7's ``optim`` give it) on
one flat vector ``x`` `n`: instead of calling a closure it ``yield``s each point at which it needs the
loss and receives ``(loss, gradient `n`)`` back, and it returns the final ``x``. Driven by
:func:`minimise` on a deterministic problem it evaluates the same points as torch's optimiser, bit for
bit, and stops after as many evaluations; several generators can run in lockstep with their
evaluations batched (the restarts of :class:`qtl.policy_search.LBFGSSearch`), each keeping its own
curvature memory, line search and stopping tests.

Bit-for-bit agreement needs torch's arithmetic in torch's order and with torch's operand types:
losses are Python floats, directional derivatives 0-dim tensors, step lengths either, and a Python
float divided by a tensor is ``reciprocal(tensor) * float`` in torch, which rounds differently from a
float division. The code below keeps those types; do not "simplify" them into floats.

Invalid points (beyond torch): the caller may answer a point with a non-finite loss, or a gradient that is
None or not finite (the rollout broke down there, e.g. a covariance that lost definiteness at an extreme ψ).
The line search then retreats halfway back towards its last valid step along the line, again and again
within its budget, as Rasmussen's ``minimize.m`` (PILCO's optimiser) does; if no valid step is found it
stays where it was, and the run ends there. Where every answer is valid nothing of this runs, so the
agreement with torch holds.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Generator
from dataclasses import dataclass

import torch
from torch import Tensor

# Sufficient decrease (Armijo) and curvature constants of the strong Wolfe conditions (torch's defaults).
WOLFE_C1 = 1e-4
WOLFE_C2 = 0.9
# The line search stops refining a bracket narrower than this (times max |d|): torch's fixed default.
BRACKET_TOLERANCE = 1e-9
# A curvature pair (s, y) enters the memory only when yᵀs exceeds this.
MIN_CURVATURE = 1e-10
# A bracket trial within this fraction of the bracket's width from an end is moved away from that end.
MIN_BRACKET_FRACTION = 0.1
# While bracketing, the next trial step lies in [t + EXTRAPOLATE_MIN (t − t_prev), EXTRAPOLATE_MAX t].
EXTRAPOLATE_MIN = 0.01
EXTRAPOLATE_MAX = 10

# What the caller sends back for a point: the loss and its gradient `n` there (None: no valid gradient there).
Evaluation = tuple[float, Tensor | None]
# The answer for a point where the caller could not evaluate (the rollout broke down): the line search retreats.
INVALID: Evaluation = (math.inf, None)
# A step length: torch mixes Python numbers and 0-dim tensors, and so does this module (see above).
Step = float | Tensor
# The generator protocol: yields points `n`, is sent evaluations, returns a value.
Asking = Generator[Tensor, Evaluation, Tensor]


@dataclass(frozen=True)
class LBFGSOptions:
    """The settings of ``torch.optim.LBFGS`` that :func:`lbfgs` honours, with torch's defaults."""

    max_iter: int = 20
    max_eval: int | None = None  # None: max_iter * 5 // 4, as torch
    lr: float = 1.0
    tolerance_grad: float = 1e-7
    tolerance_change: float = 1e-9
    history_size: int = 100

    @property
    def eval_budget(self) -> int:
        """Evaluations after which no new iteration starts (a line search may overrun it by one)."""
        return self.max_iter * 5 // 4 if self.max_eval is None else self.max_eval


@dataclass
class _LineSearchResult:
    """Where a strong-Wolfe line search ended: loss, gradient `n` and step there, and evaluations spent."""

    loss: float
    grad: Tensor
    step: Step
    evaluations: int


class _CurvatureMemory:
    """The last ``size`` pairs s = x_{k+1} − x_k, y = g_{k+1} − g_k and the initial inverse-Hessian scale."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.steps: list[Tensor] = []  # s `n`
        self.changes: list[Tensor] = []  # y `n`
        self.inverse_curvatures: list[Tensor] = []  # ρ = 1 / yᵀs
        self.scale: int | Tensor = 1  # γ = sᵀy / yᵀy of the newest pair (1 before any)

    def add(self, change: Tensor, step: Tensor) -> None:
        """Store (s, y) when yᵀs > MIN_CURVATURE, dropping the oldest pair when full."""
        curvature = change.dot(step)
        if curvature > MIN_CURVATURE:
            if len(self.steps) == self.size:
                del self.steps[0], self.changes[0], self.inverse_curvatures[0]
            self.changes.append(change)
            self.steps.append(step)
            self.inverse_curvatures.append(1.0 / curvature)
            self.scale = curvature / change.dot(change)

    def direction(self, grad: Tensor) -> Tensor:
        """−H g by the two-loop recursion (Nocedal & Wright, Algorithm 7.4), H₀ = γ I."""
        pairs = list(zip(self.steps, self.changes, self.inverse_curvatures, strict=True))
        alphas: list[Tensor] = []  # newest pair first
        q = grad.neg()
        for s, y, rho in reversed(pairs):
            alphas.append(s.dot(q) * rho)
            q.add_(y, alpha=-alphas[-1])
        r = torch.mul(q, self.scale)
        for (s, y, rho), alpha in zip(pairs, reversed(alphas), strict=True):
            beta = y.dot(r) * rho
            r.add_(s, alpha=alpha - beta)
        return r


def _cubic_minimiser(t1: Step, f1: float, g1: Tensor, t2: Step, f2: float, g2: Tensor,
                     bounds: tuple[Step, Step] | None = None) -> Step:
    """The minimiser of the cubic through (t1, f1, slope g1) and (t2, f2, g2), clipped to ``bounds``.

    Nocedal & Wright Eq. 3.59; without a real minimiser, the middle of the bounds. ``bounds``
    defaults to the interval between t1 and t2.
    """
    low, high = bounds if bounds is not None else ((t1, t2) if t1 <= t2 else (t2, t1))
    d1 = g1 + g2 - 3 * (f1 - f2) / (t1 - t2)
    d2_square = d1**2 - g1 * g2
    if not d2_square >= 0:
        return (low + high) / 2.0
    d2 = d2_square.sqrt()
    if t1 <= t2:
        minimiser = t2 - (t2 - t1) * ((g2 + d2 - d1) / (g2 - g1 + 2 * d2))
    else:
        minimiser = t1 - (t1 - t2) * ((g1 + d2 - d1) / (g1 - g2 + 2 * d2))
    return min(max(minimiser, low), high)


def invalid(answer: Evaluation) -> bool:
    """Whether an evaluation cannot be used: a non-finite loss, or a missing or non-finite gradient."""
    loss, grad = answer
    return not math.isfinite(loss) or grad is None or not bool(torch.isfinite(grad).all())


def _retreat(x: Tensor, direction: Tensor, valid: Step, step: Step, answer: Evaluation, budget: int
             ) -> Generator[Tensor, Evaluation, tuple[Step, Evaluation, int]]:
    """While the answer at ``step`` is invalid, try halfway back to the valid step ``valid``, at most ``budget`` times.

    Returns the last step tried, its answer (still invalid when the budget ran out) and the evaluations spent.
    """
    used = 0
    while invalid(answer) and used < budget:
        step = valid + (step - valid) / 2
        answer = yield x.add(direction, alpha=step)
        used += 1
    return step, answer, used


def _strong_wolfe(x: Tensor, step: Step, direction: Tensor, loss: float, grad: Tensor, slope: Tensor,
                  max_trials: int) -> Generator[Tensor, Evaluation, _LineSearchResult]:
    """A step along ``direction`` from ``x`` that meets the strong Wolfe conditions (Nocedal & Wright, Alg. 3.5-3.6).

    Brackets an acceptable step by cubic extrapolation, then zooms into the bracket by cubic
    interpolation; yields each trial point x + t d `n`. ``slope`` = gᵀd < 0 at ``x``. After the first
    trial at most ``max_trials`` more are made.
    """
    width_scale = direction.abs().max()
    grad = grad.clone(memory_format=torch.contiguous_format)
    answer = yield x.add(direction, alpha=step)
    spent = 1
    step, answer, used = yield from _retreat(x, direction, 0, step, answer, max_trials)
    spent += used
    if invalid(answer):  # no valid step along d within the budget: stay at x
        return _LineSearchResult(loss, grad, 0, spent)
    trial_loss, trial_grad = answer
    trial_slope = trial_grad.dot(direction)

    # -- Bracketing: find an interval that holds an acceptable step, or such a step itself. ----------
    prev_step: Step = 0
    prev_loss, prev_grad, prev_slope = loss, grad, slope
    trials = used
    found = False
    bracket: list[Step] = []
    bracket_loss: list[float] = []
    bracket_grad: list[Tensor] = []
    bracket_slope: list[Tensor] = []
    while trials < max_trials:
        if trial_loss > loss + WOLFE_C1 * step * slope or (trials > 1 and trial_loss >= prev_loss):
            bracket, bracket_loss = [prev_step, step], [prev_loss, trial_loss]
            bracket_grad = [prev_grad, trial_grad.clone(memory_format=torch.contiguous_format)]
            bracket_slope = [prev_slope, trial_slope]
            break
        if abs(trial_slope) <= -WOLFE_C2 * slope:
            bracket, bracket_loss, bracket_grad = [step], [trial_loss], [trial_grad]
            found = True
            break
        if trial_slope >= 0:
            bracket, bracket_loss = [prev_step, step], [prev_loss, trial_loss]
            bracket_grad = [prev_grad, trial_grad.clone(memory_format=torch.contiguous_format)]
            bracket_slope = [prev_slope, trial_slope]
            break
        # Still descending and sufficiently lower: extrapolate further along d.
        next_step = _cubic_minimiser(prev_step, prev_loss, prev_slope, step, trial_loss, trial_slope,
                                     bounds=(step + EXTRAPOLATE_MIN * (step - prev_step), step * EXTRAPOLATE_MAX))
        prev_step, prev_loss = step, trial_loss
        prev_grad, prev_slope = trial_grad.clone(memory_format=torch.contiguous_format), trial_slope
        step = next_step
        answer = yield x.add(direction, alpha=step)
        spent += 1
        trials += 1
        step, answer, used = yield from _retreat(x, direction, prev_step, step, answer, max_trials - trials)
        spent, trials = spent + used, trials + used
        if invalid(answer):  # nothing valid beyond the last trial, which decreased the loss enough: take it
            return _LineSearchResult(prev_loss, prev_grad, prev_step, spent)
        trial_loss, trial_grad = answer
        trial_slope = trial_grad.dot(direction)
    if trials == max_trials:  # out of trials: the better of the start and the last trial
        bracket, bracket_loss, bracket_grad = [0, step], [loss, trial_loss], [grad, trial_grad]

    # -- Zoom: shrink the bracket around an acceptable step. -------------------------------------------
    low, high = (0, 1) if bracket_loss[0] <= bracket_loss[-1] else (1, 0)
    stalled = False
    while not found and trials < max_trials:
        if abs(bracket[1] - bracket[0]) * width_scale < BRACKET_TOLERANCE:
            break
        step = _cubic_minimiser(bracket[0], bracket_loss[0], bracket_slope[0],
                                bracket[1], bracket_loss[1], bracket_slope[1])
        # Keep the trial off the bracket's ends: a trial close to an end twice running (or on or
        # beyond an end) is moved MIN_BRACKET_FRACTION of the width inside.
        top, bottom = max(bracket), min(bracket)
        margin = MIN_BRACKET_FRACTION * (top - bottom)
        if min(top - step, step - bottom) < margin:
            if stalled or step >= top or step <= bottom:
                step = top - margin if abs(step - top) < abs(step - bottom) else bottom + margin
                stalled = False
            else:
                stalled = True
        else:
            stalled = False

        answer = yield x.add(direction, alpha=step)
        spent += 1
        trials += 1
        step, answer, used = yield from _retreat(x, direction, bracket[low], step, answer, max_trials - trials)
        spent, trials = spent + used, trials + used
        if invalid(answer):  # nothing valid between the bracket's low end and this trial: the low end it is
            break
        trial_loss, trial_grad = answer
        trial_slope = trial_grad.dot(direction)

        if trial_loss > loss + WOLFE_C1 * step * slope or trial_loss >= bracket_loss[low]:
            # Not sufficiently lower, or not below the low end: the trial becomes the high end.
            bracket[high], bracket_loss[high] = step, trial_loss
            bracket_grad[high] = trial_grad.clone(memory_format=torch.contiguous_format)
            bracket_slope[high] = trial_slope
            low, high = (0, 1) if bracket_loss[0] <= bracket_loss[1] else (1, 0)
            continue
        if abs(trial_slope) <= -WOLFE_C2 * slope:
            found = True
        elif trial_slope * (bracket[high] - bracket[low]) >= 0:  # the minimum lies beyond low: low becomes high
            bracket[high], bracket_loss[high] = bracket[low], bracket_loss[low]
            bracket_grad[high], bracket_slope[high] = bracket_grad[low], bracket_slope[low]
        bracket[low], bracket_loss[low] = step, trial_loss
        bracket_grad[low] = trial_grad.clone(memory_format=torch.contiguous_format)
        bracket_slope[low] = trial_slope

    return _LineSearchResult(bracket_loss[low], bracket_grad[low], bracket[low], spent)


def lbfgs(x: Tensor, options: LBFGSOptions) -> Asking:
    """Minimise from ``x`` `n`: yield each point `n` to evaluate, be sent ``(loss, gradient `n`)``, return the final x.

    One ``torch.optim.LBFGS(..., line_search_fn="strong_wolfe").step(closure)`` of a fresh optimiser
    with the same ``options``; the final x is the line search's last accepted point (where torch
    leaves the parameters), and it need not be the best point evaluated.
    """
    x = x.detach().clone(memory_format=torch.contiguous_format)
    answer = yield x
    if invalid(answer):  # no valid start: nothing to do
        return x
    loss, grad = answer
    spent = 1
    if grad.abs().max() <= options.tolerance_grad:
        return x
    memory = _CurvatureMemory(options.history_size)
    direction = step = prev_grad = None
    for iteration in range(1, options.max_iter + 1):
        # -- The search direction: steepest descent first, then the L-BFGS direction. -----------
        if iteration == 1:
            direction = grad.neg()
        else:
            memory.add(grad.sub(prev_grad), direction.mul(step))
            direction = memory.direction(grad)
        prev_grad, prev_loss = grad, loss
        # -- The step: 1 (lr), or at first at most 1 / ‖g‖₁. ----------------------------------------
        step = min(1.0, 1.0 / grad.abs().sum()) * options.lr if iteration == 1 else options.lr
        slope = grad.dot(direction)
        if slope > -options.tolerance_change:  # not a descent direction (any longer)
            break
        found = yield from _strong_wolfe(x, step, direction, loss, grad, slope,
                                         max_trials=options.eval_budget - spent)
        loss, grad, step = found.loss, found.grad, found.step
        x = x.add(direction, alpha=step)
        spent += found.evaluations
        # -- Stopping tests, in torch's order. ------------------------------------------------------
        if iteration == options.max_iter or spent >= options.eval_budget:
            break
        if grad.abs().max() <= options.tolerance_grad:
            break
        if direction.mul(step).abs().max() <= options.tolerance_change:
            break
        if abs(loss - prev_loss) < options.tolerance_change:
            break
    return x


def minimise(function: Callable[[Tensor], Evaluation], x: Tensor, options: LBFGSOptions) -> Tensor:
    """Drive :func:`lbfgs` alone: ``function(point)`` gives (loss, gradient `n`); the final x `n`."""
    run = lbfgs(x, options)
    point = next(run)
    while True:
        try:
            point = run.send(function(point))
        except StopIteration as stop:
            return stop.value
