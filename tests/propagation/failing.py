"""A batch of restarts one of which fails: a linear policy whose action covariance one restart makes indefinite."""

from __future__ import annotations

import pytest
import torch
from torch import Tensor, nn

from qtl.gaussian import Gaussian, GaussianMap, MomentMatch
from qtl.kernels import Engine
from qtl.kernels.engine import DEFAULT_ENGINE
from qtl.policies import LinearPolicy
from qtl.propagation import MomentMatching
from tests.conftest import make_gp
from tests.helpers import quadratic_reward

DTYPE = torch.float64
BAD = 1  # the failing restart of three
BAD_SHIFT = -50.0  # cov u − 50: the GP input's covariance is far from positive-definite
HORIZON = 5
ENGINES = ("reference", "fused", "native")  # kernels.moments; native with the native exp sums


class ShiftedLinearPolicy(LinearPolicy):
    """u = W y + b whose moment map adds diag(``shift``) to cov u (a fixed part of ψ): negative, it is indefinite."""

    def __init__(self, input_dim: int, output_dim: int, generator: torch.Generator | None = None) -> None:
        super().__init__(input_dim, output_dim, generator=generator)
        self.shift = nn.Parameter(torch.zeros(output_dim, dtype=DTYPE), requires_grad=False)

    def prepare(self, engine: Engine = DEFAULT_ENGINE) -> GaussianMap:
        """The linear policy's exact moments, cov u shifted by diag(shift)."""
        linear, shift = super().prepare(engine), self.shift

        def moments(state: Gaussian) -> MomentMatch:
            out = linear(state)
            return MomentMatch(out.mean, out.cov + torch.diag_embed(shift), out.cross_cov, out.gain)

        return moments


def engine_of(moments: str) -> Engine:
    """The engine of ``kernels.moments=moments`` (native: skipped where the native kernels are not built)."""
    if moments != "native":
        return Engine(moments=moments)
    engine = Engine.resolve("auto", "auto")
    if not engine.native:
        pytest.skip("the native kernels are not built")
    return engine


def system(moments: str) -> tuple[ShiftedLinearPolicy, MomentMatching, Gaussian]:
    """A plain shifted policy, a propagator on it (3-D state with an angle, 1-D action) and a start."""
    policy = ShiftedLinearPolicy(4, 1, generator=torch.Generator().manual_seed(3))
    propagator = MomentMatching(make_gp(40, 3, 1, (1,), seed=22), policy, quadratic_reward(3, (1,)), angle_dims=(1,),
                                engine=engine_of(moments))
    return policy, propagator, Gaussian(torch.tensor([0.1, 0.2, -0.1], dtype=DTYPE), 0.01 * torch.eye(3, dtype=DTYPE))


def restart_states(policy: ShiftedLinearPolicy, bad_shift: float = BAD_SHIFT) -> list[dict[str, Tensor]]:
    """Three restarts' ψ (W spread), restart BAD's cov u shifted by ``bad_shift``."""
    gen = torch.Generator().manual_seed(1)
    states = []
    for restart in range(3):
        state = {name: value.detach().clone() for name, value in policy.state_dict().items()}
        state["weight"] += 0.2 * restart * torch.randn(state["weight"].shape, generator=gen, dtype=DTYPE)
        if restart == BAD:
            state["shift"].fill_(bad_shift)
        states.append(state)
    return states


def solo(policy: ShiftedLinearPolicy, propagator: MomentMatching, start: Gaussian,
         state: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
    """V and ∂V/∂(W, b) flattened of one restart's ψ, rolled out alone (unbatched)."""
    policy.load_state_dict(state)
    policy.zero_grad()
    value = propagator.expected_return(start, HORIZON)
    value.backward()
    return value.detach(), torch.cat([policy.weight.grad.reshape(-1), policy.bias.grad.reshape(-1)])
