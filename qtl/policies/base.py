"""The interface every policy π_ψ offers: deterministic actions and exact moments at Gaussian inputs."""

from __future__ import annotations

from abc import ABC, abstractmethod

from torch import Tensor, nn

from qtl.gaussian import Gaussian, GaussianMap, MomentMatch


class Policy(nn.Module, ABC):
    """A policy u = π_ψ(y) of the (angle-augmented) state features y; ψ are its parameters.

    ``forward`` acts on plain tensors (the real system); ``prepare`` returns the map of
    Gaussian inputs with exact output moments, with everything that depends only on ψ
    computed once (a rollout prepares once and calls it at every step).
    """

    input_dim: int
    output_dim: int

    @abstractmethod
    def forward(self, x: Tensor) -> Tensor:
        """Actions `... x F` for features `... x D`."""

    @abstractmethod
    def prepare(self) -> GaussianMap:
        """The moment-matching map of this policy with its ψ-only quantities precomputed."""

    def moments(self, state: Gaussian) -> MomentMatch:
        """Mean `... x F`, covariance `... x F x F` and input–output terms `... x D x F` of π(y)."""
        return self.prepare()(state)
