"""How a state steps from the GP's output: x + Δ, or MC-PILCO's speed integration (particles, moment matching).

In speed integration the GP predicts the velocities' changes and the positions follow by the trapezoid rule.
With positions q and their velocities q̇ in the state, a control period T and the GP's draw Δq̇_t of the
velocities' change (Amadio et al. 2022, "Model-based policy search using Monte Carlo gradient estimation
with real systems application", the speed-integration model):

    q̇_{t+1} = q̇_t + Δq̇_t,    q_{t+1} = q_t + T q̇_t + (T/2) Δq̇_t   (= q_t + T (q̇_t + q̇_{t+1}) / 2),

and every other state dimension (neither a position nor a velocity) steps by its own GP draw, x + Δ. The
GP's outputs for the positions are not used: a particle's position then stays consistent with its velocity,
which a separate GP of Δq cannot promise. Both maps are linear, x_{t+1} = x_t A + Δ J with A `D x D`
and J `E' x D` (E' = the D − K modelled outputs), so a Gaussian step N(m, diag v) of Δ gives the state's
predictive N(x A + m J, Jᵀ diag(v) J). Under moment matching (x_t, Δ) is jointly Gaussian with cov[x_t, Δ] = C,
and x_{t+1} has the exact moments μ A + μ_Δ J and Aᵀ Σ A + Jᵀ Σ_Δ J + Aᵀ C J + (Aᵀ C J)ᵀ (:meth:`moment_terms`).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from qtl.gaussian import symmetrize
from qtl.task import Kinematics, check_kinematics

# How a state steps: x + Δ in every dimension, or positions integrated from their velocities.
INTEGRATION = ("delta", "speed")


class DeltaIntegration:
    """The step x_{t+1} = x_t + Δ in every dimension: the GP models every output."""

    def step(self, x: Tensor, delta: Tensor) -> Tensor:
        """x_{t+1} `... x D` from x_t and the draws Δ `... x D`."""
        return x + delta

    def covariance(self, variance: Tensor) -> Tensor:
        """diag(v) `... x D x D`: the state's covariance from independent draws of variance v `... x D`."""
        return torch.diag_embed(variance)

    def modelled(self, noise: Tensor) -> Tensor:
        """The columns of the modelled outputs of ``noise`` `... x D`: all of them."""
        return noise

    def select_outputs(self, data: dict[str, Tensor]) -> dict[str, Tensor]:
        """The cache's tensors of the modelled outputs: all of them."""
        return data

    def moment_terms(
        self, mean: Tensor, cov: Tensor, delta_mean: Tensor, delta_cov: Tensor, cov_x_delta: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """The moments of the summands x_t and Δ of x_{t+1} = x_t + Δ (and their cross-covariance): as given."""
        return mean, cov, delta_mean, delta_cov, cov_x_delta


class LinearIntegration:
    """The linear step x_{t+1} = x_t A + Δ J: ``advance`` A `D x D`, ``scatter`` J `E' x D`.

    ``outputs``: the state dimensions (E' of them, in order) whose GP outputs the draws Δ are; the others' are not used.
    """

    def __init__(self, advance: Tensor, scatter: Tensor, outputs: Sequence[int]) -> None:
        if advance.shape != (advance.shape[0],) * 2 or scatter.shape != (len(outputs), advance.shape[0]):
            raise ValueError(f"advance must be `D x D` and scatter `{len(outputs)} x D`, got "
                             f"{tuple(advance.shape)} and {tuple(scatter.shape)}")
        self.advance, self.scatter, self.outputs = advance, scatter, tuple(int(d) for d in outputs)

    def step(self, x: Tensor, delta: Tensor) -> Tensor:
        """x_{t+1} `... x D` from x_t `... x D` and the draws Δ of the modelled outputs `... x E'`."""
        return x @ self.advance + delta @ self.scatter

    def covariance(self, variance: Tensor) -> Tensor:
        """Jᵀ diag(v) J `... x D x D`: the state's covariance from independent draws of variance v `... x E'`."""
        return self.scatter.mT @ (variance[..., :, None] * self.scatter)

    def modelled(self, noise: Tensor) -> Tensor:
        """The columns `... x E'` of the modelled outputs of ``noise`` `... x D` (each reads its own)."""
        return noise[..., list(self.outputs)]

    def select_outputs(self, data: dict[str, Tensor]) -> dict[str, Tensor]:
        """The cache's per-output tensors of the modelled outputs only (the shared inputs as they are)."""
        return select_outputs(data, self.outputs)

    def moment_terms(
        self, mean: Tensor, cov: Tensor, delta_mean: Tensor, delta_cov: Tensor, cov_x_delta: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """The moments of the summands x_t A and Δ J of x_{t+1} (and their cross-covariance Aᵀ C J), exact.

        From μ `... x D`, Σ `... x D x D`, μ_Δ `... x E'`, Σ_Δ `... x E' x E'` and C = cov[x_t, Δ] `... x D x E'`:
        μ A, Aᵀ Σ A, μ_Δ J, Jᵀ Σ_Δ J (both exactly symmetric) `... x D (x D)` and Aᵀ C J `... x D x D`.
        """
        advance, scatter = self.advance, self.scatter
        return (mean @ advance, symmetrize(advance.mT @ cov @ advance), delta_mean @ scatter,
                symmetrize(scatter.mT @ delta_cov @ scatter), advance.mT @ cov_x_delta @ scatter)


class SpeedIntegration(LinearIntegration):
    """The speed integration's linear step x_{t+1} = x_t A + Δ J of a ``state_dim``-D state (the module docstring).

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
        outputs = tuple(d for d in range(state_dim) if d not in positions)
        column = {d: i for i, d in enumerate(outputs)}
        advance = torch.eye(state_dim, dtype=torch.float64)
        scatter = torch.zeros(len(outputs), state_dim, dtype=torch.float64)
        scatter[range(len(outputs)), list(outputs)] = 1.0
        for p, v in zip(positions, velocities, strict=True):
            advance[v, p] = self.period  # q + T q̇
            scatter[column[v], p] = 0.5 * self.period  # + (T/2) Δq̇
        super().__init__(advance.to(dtype=dtype, device=device), scatter.to(dtype=dtype, device=device), outputs)


def select_outputs(data: dict[str, Tensor], outputs: Sequence[int]) -> dict[str, Tensor]:
    """The cache's per-output tensors of ``outputs`` only (the shared inputs `... x n x D_in` as they are)."""
    index = torch.tensor(list(outputs), dtype=torch.long, device=data["beta"].device)
    output_dim = {"K_inv": -3, "prior_inv": -3, "update_root": -3, "beta": -2, "lengthscales": -2,
                  "signal_variance": -1, "noise_variance": -1}
    return {k: v.index_select(output_dim[k], index) if k in output_dim else v for k, v in data.items()}


def make_integration(
    name: str, state_dim: int, kinematics: Kinematics | None, dtype: torch.dtype, device: torch.device | str
) -> DeltaIntegration | LinearIntegration:
    """The step ``name`` (one of INTEGRATION) of a ``state_dim``-D state; ``speed`` needs ``kinematics``."""
    if name == "delta":
        return DeltaIntegration()
    if name != "speed" or kinematics is None:
        raise ValueError(f"integration {name!r} needs to be delta, or speed with kinematics")
    return SpeedIntegration(state_dim, kinematics, dtype, device)
