"""The rollout benchmarks' synthetic case: a cart-pole-shaped GP on random transitions, an RBF policy, the tip reward.

State [x, ẋ, θ, θ̇] with θ an angle, GP input [x, ẋ, θ̇, sin θ, cos θ, u] (E = 4 outputs, 6-D input), an RBF
policy with 50 basis functions squashed to ±10, the tip-distance reward; H = 50 steps.
"""

from __future__ import annotations

import numpy as np
import torch

from qtl.envs.rewards import SaturatingReward
from qtl.features import AngleFeatures
from qtl.gaussian import Gaussian
from qtl.kernels.engine import DEFAULT_ENGINE, Engine
from qtl.models import DynamicsGP
from qtl.policies import RBFPolicy, SquashedPolicy
from qtl.propagation import MomentMatching
from qtl.rewards import ExpectedSaturatingReward

HORIZON = 50
STATE_DIM = 4
ANGLE_DIMS = (2,)
NUM_BASIS = 50
ACTION_BOUND = 10.0
POLE_LENGTH = 0.6
COST_WIDTH = 0.25


def cartpole_reward() -> ExpectedSaturatingReward:
    """Tip distance to the upright target, width 0.25 m."""
    tip = np.array([[1.0, 0.0, 0.0, POLE_LENGTH, 0.0], [0.0, 0.0, 0.0, 0.0, -POLE_LENGTH]])
    spec = SaturatingReward(
        state_dim=STATE_DIM,
        angle_dims=ANGLE_DIMS,
        target=(0.0, 0.0, 0.0, 0.0, -1.0),
        weight=tuple(map(tuple, tip.T @ tip)),
        width=COST_WIDTH,
    )
    return ExpectedSaturatingReward.from_spec(spec)


def make_case(n: int, dtype: torch.dtype, engine: Engine = DEFAULT_ENGINE) -> tuple[MomentMatching, Gaussian]:
    """A GP on n synthetic cart-pole-like transitions, an RBF policy, the start distribution; moments by ``engine``."""
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(n, STATE_DIM, generator=gen, dtype=torch.float64) * torch.tensor([1.0, 2.0, 3.0, 4.0])
    u = ACTION_BOUND * (2 * torch.rand(n, 1, generator=gen, dtype=torch.float64) - 1)
    feats = AngleFeatures(STATE_DIM, ANGLE_DIMS)(x)
    delta = 0.1 * torch.stack([x[:, 1], torch.sin(x[:, 2]) + 0.05 * u[:, 0], x[:, 3], torch.cos(x[:, 2]) * x[:, 3]], -1)
    model = DynamicsGP(torch.cat([feats, u], -1), delta + 0.01 * torch.randn(n, STATE_DIM, generator=gen))
    policy = SquashedPolicy(RBFPolicy(feats.shape[-1], 1, NUM_BASIS, generator=gen), ACTION_BOUND).to(dtype)
    propagator = MomentMatching(model.posterior_cache(), policy, cartpole_reward(), angle_dims=ANGLE_DIMS, dtype=dtype,
                                engine=engine)
    start = Gaussian(torch.zeros(STATE_DIM, dtype=dtype), 0.01 * torch.eye(STATE_DIM, dtype=dtype))
    return propagator, start
