"""Policy improvement: maximise the predicted return V^π(ψ) by gradients (Algorithm 1, lines 6-9)."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from qtl.errors import NonFiniteObjective

log = logging.getLogger(__name__)

# Parameters with a spread below this are perturbed on this scale instead.
MIN_PERTURBATION_SCALE = 1e-3



@dataclass(frozen=True)
class SearchResult:
    """Outcome of a policy search: the best predicted return and what it cost."""

    value: float
    evaluations: int
    run_values: list[float]  # best value of each run (-inf for a run that evaluated nothing finite)


def _perturb(policy: nn.Module, scale: float, generator: torch.Generator | None) -> None:
    """ψ ← ψ + scale · spread(ψ) · ε, ε ~ N(0, I), per parameter tensor."""
    with torch.no_grad():
        for p in policy.parameters():
            spread = p.std() if p.numel() > 1 else p.abs().squeeze()
            spread = max(float(spread), MIN_PERTURBATION_SCALE)
            noise = torch.randn(p.shape, generator=generator, dtype=p.dtype).to(p.device)
            p.add_(scale * spread * noise)


def _checked(value: Tensor) -> Tensor:
    if not torch.isfinite(value).all():
        raise NonFiniteObjective(f"predicted return is {value.item()}")
    return value


class _BestSeen:
    """The best ψ an objective has been evaluated at, and its value."""

    def __init__(self, policy: nn.Module) -> None:
        self.policy = policy
        self.value = -math.inf
        self.state: dict[str, Tensor] | None = None
        self.calls = 0  # evaluations of the objective, failed ones included

    def offer(self, value: float) -> None:
        if value > self.value:
            self.value = value
            self.state = {k: v.detach().clone() for k, v in self.policy.state_dict().items()}


class _RestartingSearch:
    """Runs from the current ψ and from ``restarts − 1`` perturbations of it; keeps the best ψ seen.

    An evaluation whose predicted return (or its gradient) is not finite, or whose propagation
    breaks down numerically, ends its run: the run keeps the best ψ it evaluated before.
    """

    def __init__(self, restarts: int, perturbation: float) -> None:
        if restarts < 1:
            raise ValueError(f"restarts must be >= 1, got {restarts}")
        if perturbation < 0:
            raise ValueError(f"perturbation must be >= 0, got {perturbation}")
        self.restarts = restarts
        self.perturbation = perturbation

    def _run(self, params: list[nn.Parameter], objective: Callable[[], Tensor], tick: Callable[[], None]) -> None:
        raise NotImplementedError

    def __call__(
        self,
        policy: nn.Module,
        objective: Callable[[], Tensor],
        *,
        generator: torch.Generator | None = None,
        tick: Callable[[], None] = lambda: None,
    ) -> SearchResult:
        """Maximise ``objective()`` (a scalar of ψ = ``policy.parameters()``); leave the best ψ in ``policy``."""
        start = {k: v.detach().clone() for k, v in policy.state_dict().items()}
        best = _BestSeen(policy)
        run_values, evaluations = [], 0
        for run in range(self.restarts):
            policy.load_state_dict(start)
            if run > 0:
                _perturb(policy, self.perturbation, generator)
            seen = _BestSeen(policy)

            def tracked(seen: _BestSeen = seen) -> Tensor:
                seen.calls += 1
                value = _checked(objective())
                seen.offer(float(value.detach()))
                return value

            params = [p for p in policy.parameters() if p.requires_grad]
            try:
                self._run(params, tracked, tick)
            except (NonFiniteObjective, torch.linalg.LinAlgError) as err:
                log.warning("policy search run %d stopped at a numerically invalid ψ (%s); "
                            "it keeps the best ψ it evaluated", run, err)
            run_values.append(seen.value)
            evaluations += seen.calls
            if seen.state is not None and seen.value > best.value:
                best.value, best.state = seen.value, seen.state
        if best.state is None:
            raise NonFiniteObjective("no policy search run evaluated a finite predicted return")
        policy.load_state_dict(best.state)
        return SearchResult(value=best.value, evaluations=evaluations, run_values=run_values)


class LBFGSSearch(_RestartingSearch):
    """L-BFGS with a strong-Wolfe line search, ``max_iter`` evaluations per run."""

    def __init__(self, max_iter: int = 100, restarts: int = 2, perturbation: float = 0.1) -> None:
        super().__init__(restarts, perturbation)
        if max_iter < 1:
            raise ValueError(f"max_iter must be >= 1, got {max_iter}")
        self.max_iter = max_iter

    def _run(self, params: list[nn.Parameter], objective: Callable[[], Tensor], tick: Callable[[], None]) -> None:
        optimiser = torch.optim.LBFGS(
            params, lr=1.0, max_iter=self.max_iter, max_eval=self.max_iter, line_search_fn="strong_wolfe"
        )

        def closure() -> Tensor:
            optimiser.zero_grad()
            loss = -_checked(objective())
            loss.backward()
            for p in params:
                if p.grad is not None and not torch.isfinite(p.grad).all():
                    raise NonFiniteObjective("gradient of the predicted return is not finite")
            tick()
            return loss

        optimiser.step(closure)


class AdamSearch(_RestartingSearch):
    """Adam for ``steps`` steps per run (suits stochastic objectives)."""

    def __init__(self, steps: int = 300, lr: float = 0.01, restarts: int = 1, perturbation: float = 0.1) -> None:
        super().__init__(restarts, perturbation)
        if steps < 1 or lr <= 0:
            raise ValueError(f"steps must be >= 1 and lr > 0, got {steps} and {lr}")
        self.steps, self.lr = steps, lr

    def _run(self, params: list[nn.Parameter], objective: Callable[[], Tensor], tick: Callable[[], None]) -> None:
        optimiser = torch.optim.Adam(params, lr=self.lr)
        for _ in range(self.steps):
            optimiser.zero_grad()
            loss = -_checked(objective())
            loss.backward()
            optimiser.step()
            tick()
