"""MC-PILCO's speed integration: the GP predicts the velocities' changes, the positions follow by the trapezoid rule.

With positions q and their velocities q̇ in the state, a control period T and the GP's draw Δq̇_t of the
velocities' change (Amadio et al. 2022, "Model-based policy search using Monte Carlo gradient estimation
with real systems application", the speed-integration model):

    q̇_{t+1} = q̇_t + Δq̇_t,    q_{t+1} = q_t + T q̇_t + (T/2) Δq̇_t   (= q_t + T (q̇_t + q̇_{t+1}) / 2),

and every other state dimension (neither a position nor a velocity) steps by its own GP draw, x + Δ. The
GP's outputs for the positions are not used: a particle's position then stays consistent with its velocity,
which a separate GP of Δq cannot promise. Both maps are linear, x_{t+1} = x_t A + Δ J with A `D x D`
and J `E' x D` (E' = the D − K modelled outputs), so a Gaussian step N(m, diag v) of Δ gives the state's
predictive N(x A + m J, Jᵀ diag(v) J).
"""

from __future__ import annotations

import torch
from torch import Tensor

from qtl.task import Kinematics, check_kinematics


class SpeedIntegration:
    """The linear step x_{t+1} = x_t A + Δ J of a ``state_dim``-D state (see the module docstring).

    ``kinematics``: the positions, their velocities (position k's at ``velocities[k]``) and the period T in
    seconds between two learner steps. ``outputs``: the state dimensions the GP's draws Δ stand for, in order
    (all but the positions).
    """

    def __init__(
        self,
        state_dim: int,
        kinematics: Kinematics,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str = "cpu",
    ) -> None:
        positions, velocities, period = kinematics
        check_kinematics(state_dim, positions, velocities, period)  # a Task's are checked; one made by hand may not be
        self.state_dim = state_dim
        self.period = float(period)
        self.outputs = tuple(d for d in range(state_dim) if d not in positions)
        column = {d: i for i, d in enumerate(self.outputs)}
        advance = torch.eye(state_dim, dtype=torch.float64)
        scatter = torch.zeros(len(self.outputs), state_dim, dtype=torch.float64)
        scatter[range(len(self.outputs)), list(self.outputs)] = 1.0
        for p, v in zip(positions, velocities, strict=True):
            advance[v, p] = self.period  # q + T q̇
            scatter[column[v], p] = 0.5 * self.period  # + (T/2) Δq̇
        self.advance, self.scatter = advance.to(dtype=dtype, device=device), scatter.to(dtype=dtype, device=device)

    def step(self, x: Tensor, delta: Tensor) -> Tensor:
        """x_{t+1} `... x D` from x_t `... x D` and the draws Δ of the modelled outputs `... x E'`."""
        return x @ self.advance + delta @ self.scatter

    def covariance(self, variance: Tensor) -> Tensor:
        """Jᵀ diag(v) J `... x D x D`: the state's covariance from independent draws of variance v `... x E'`."""
        return self.scatter.mT @ (variance[..., :, None] * self.scatter)
