"""The interface every policy π_ψ offers: deterministic actions and exact moments at Gaussian inputs."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable

import torch
from torch import Tensor, nn

from qtl.gaussian import Gaussian, GaussianMap, MomentMatch
from qtl.kernels.engine import DEFAULT_ENGINE, Engine


class Policy(nn.Module, ABC):
    """A policy u = π_ψ(y) of the (angle-augmented) state features y; ψ are its parameters.

    ``forward`` acts on plain tensors (the real system); ``prepare`` returns the map of
    Gaussian inputs with exact output moments, with everything that depends only on ψ
    computed once (a rollout prepares once and calls it at every step).

    ``batch_shape``: leading dimensions that every ψ tensor carries (`R`, restarts searched
    together; empty for one policy, see :mod:`qtl.policies.batching`). A batched policy's
    moment map broadcasts R against the batch of its Gaussian input, and ``forward`` takes
    features `R x S x D` (S points per restart, or anything that broadcasts to it).
    """

    input_dim: int
    output_dim: int
    batch_shape: torch.Size = torch.Size()

    def per_point(self, psi: Tensor) -> Tensor:
        """A ψ-derived `R x ...` as `R x 1 x ...`, to broadcast against inputs `R x S x D`; as is when unbatched."""
        return psi.unsqueeze(len(self.batch_shape)) if self.batch_shape else psi

    @abstractmethod
    def forward(self, x: Tensor) -> Tensor:
        """Actions `... x F` for features `... x D`."""

    @abstractmethod
    def prepare(self, engine: Engine = DEFAULT_ENGINE) -> GaussianMap:
        """The moment-matching map of this policy with its ψ-only quantities precomputed, computed by ``engine``."""

    def actions(self, engine: Engine = DEFAULT_ENGINE) -> Callable[[Tensor], Tensor]:
        """``forward`` with its ψ-only quantities made once (a particle rollout takes it once, calls it each step).

        ``engine``: for a policy whose forward has twins (the RBF network); the others ignore it.
        """
        return self.forward

    def set_dropout(self, rate: float, generator: torch.Generator | None = None) -> None:
        """Drop parts of the policy at random in ``forward`` with probability ``rate`` (0: off); some policies can."""
        if rate != 0.0:
            raise ValueError(f"{type(self).__name__} has no dropout: use policy=rbf_network, or optimizer.dropout=0")

    def moments(self, state: Gaussian, engine: Engine = DEFAULT_ENGINE) -> MomentMatch:
        """Mean `... x F`, covariance `... x F x F` and input–output terms `... x D x F` of π(y), by ``engine``."""
        return self.prepare(engine)(state)
