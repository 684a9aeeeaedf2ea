"""The interface every policy π_ψ offers: deterministic actions, moments, and ψ for transfer."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping

import torch
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

    def get_psi(self) -> dict[str, Tensor]:
        """ψ as a flat ``{name: tensor}`` dict of detached copies (what transfer copies)."""
        return {name: p.detach().clone() for name, p in self.named_parameters()}

    def set_psi(self, psi: Mapping[str, Tensor]) -> None:
        """Load ψ from :meth:`get_psi` of a policy of the same structure; names and shapes must match."""
        own = dict(self.named_parameters())
        if set(psi) != set(own):
            raise ValueError(f"ψ names {sorted(psi)} do not match this policy's {sorted(own)}")
        for name, value in psi.items():
            if tuple(value.shape) != tuple(own[name].shape):
                raise ValueError(f"ψ[{name!r}] has shape {tuple(value.shape)}, expected {tuple(own[name].shape)}")
        with torch.no_grad():
            for name, value in psi.items():
                own[name].copy_(value.to(own[name]))
