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

Outputs whose Δ the data showed constant (:mod:`qtl.models.constant`) are deterministic: their Δ c is no GP draw
but an offset, x_{t+1} = x_t A + Δ J + b with b = c J_c (J_c their rows of the map), which shifts the mean and adds
no variance or covariance (:class:`OffsetIntegration`). The delta step with such outputs is this map with A = I and
J the rows of the GP's outputs; both propagators take it from the model (``for_model``).
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
    """The step x_{t+1} = x_t + Δ in every dimension: the GP models every output (of a ``state_dim``-D state)."""

    def __init__(self, state_dim: int | None = None) -> None:
        self.state_dim = state_dim

    def step(self, x: Tensor, delta: Tensor) -> Tensor:
        """x_{t+1} `... x D` from x_t and the draws Δ `... x D`."""
        return x + delta

    def covariance(self, variance: Tensor) -> Tensor:
        """diag(v) `... x D x D`: the state's covariance from independent draws of variance v `... x D`."""
        return torch.diag_embed(variance)

    def modelled(self, noise: Tensor) -> Tensor:
        """The columns of the modelled outputs of ``noise`` `... x D`: all of them."""
        return noise

    def for_model(self, data: dict[str, Tensor]) -> tuple[DeltaIntegration | LinearIntegration, dict[str, Tensor]]:
        """The step and the cache's tensors for a model's cache ``data``: as they are; it must model every output.

        A model with deterministic outputs (constant Δ) gives x_{t+1} = x_t + Δ J + b instead: J the rows of the
        GP's outputs, b their constant Δ (:class:`OffsetIntegration`).
        """
        outputs = _model_outputs(data)
        constant, _ = _model_constants(data)
        if constant:
            state_dim = len(outputs) + len(constant) if self.state_dim is None else self.state_dim
            eye = torch.eye(state_dim, dtype=data["beta"].dtype, device=data["beta"].device)
            return _with_constants(eye, eye, tuple(range(state_dim)), data)
        if self.state_dim is not None and outputs != tuple(range(self.state_dim)):
            raise ValueError(f"integration delta steps every state dimension, but the GP models outputs "
                             f"{list(outputs)} of {self.state_dim}: fit it on all of them")
        return self, data

    def lag_covariance(self, cov: Tensor, cov_x_delta: Tensor) -> Tensor:
        """cov(x_t, x_{t+1}) = Σ + C `... x D x D` from Σ and C = cov[x_t, Δ] `... x D x D`."""
        return cov + cov_x_delta

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

    def for_model(self, data: dict[str, Tensor]) -> tuple[LinearIntegration, dict[str, Tensor]]:
        """The step and the cache's tensors for a model's cache ``data``.

        A model of exactly the modelled outputs is taken as it is; one of more (e.g. of every state dimension,
        fitted before models held their outputs) is cut to the modelled outputs (exact: the outputs are independent
        GPs); one with deterministic outputs (constant Δ) gives an :class:`OffsetIntegration`. One that lacks a
        modelled output raises ValueError.
        """
        outputs = _model_outputs(data)
        if _model_constants(data)[0]:  # deterministic outputs: their Δ in the offset b
            return _with_constants(self.advance, self.scatter, self.outputs, data)
        if outputs == self.outputs:
            return self, data
        if set(self.outputs) <= set(outputs):
            return self, select_outputs(data, self.outputs)
        raise ValueError(f"the step models outputs {list(self.outputs)}, the GP outputs {list(outputs)}: fit the "
                         "GP on the step's outputs (or on all of them)")

    def lag_covariance(self, cov: Tensor, cov_x_delta: Tensor) -> Tensor:
        """cov(x_t, x_{t+1}) = Σ A + C J `... x D x D` from Σ `... x D x D` and C = cov[x_t, Δ] `... x D x E'`."""
        return cov @ self.advance + cov_x_delta @ self.scatter

    def moment_terms(
        self, mean: Tensor, cov: Tensor, delta_mean: Tensor, delta_cov: Tensor, cov_x_delta: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """The moments of the summands x_t A and Δ J of x_{t+1} (and their cross-covariance Aᵀ C J), exact.

        From μ `... x D`, Σ `... x D x D`, μ_Δ `... x E'`, Σ_Δ `... x E' x E'` and C = cov[x_t, Δ] `... x D x E'`:
        μ A, Aᵀ Σ A, μ_Δ J, Jᵀ Σ_Δ J (both exactly symmetric) `... x D (x D)` and Aᵀ C J `... x D x D`.
        """
        advance, scatter = self.advance, self.scatter
        batch = cov.shape[:-2]
        if len(batch) != 1 or delta_cov.shape[:-2] != batch or cov_x_delta.shape[:-2] != batch:
            return (mean @ advance, symmetrize(advance.mT @ cov @ advance), delta_mean @ scatter,
                    symmetrize(scatter.mT @ delta_cov @ scatter), advance.mT @ cov_x_delta @ scatter)
        # One batch dimension (the rollouts' usual case): each product one bmm against the constant maps expanded
        # (no autograd node of their own), and M/2 + (M/2)ᵀ with M/2 = Aᵀ Σ (A/2) (exact halving) is bit for bit
        # symmetrize(M): fewer dispatched ops and autograd nodes, the same values.
        maps = self.__dict__.get("_moment_maps")
        if maps is None or maps[0] is not advance or maps[1] is not scatter:
            maps = (advance, scatter, advance.mT.contiguous(), 0.5 * advance, scatter.mT.contiguous(), 0.5 * scatter)
            self._moment_maps = maps
        size, d, e = batch[0], advance.shape[0], scatter.shape[0]
        advance_t, advance_half = maps[2].expand(size, d, d), maps[3].expand(size, d, d)
        scatter_t, scatter_half = maps[4].expand(size, d, e), maps[5].expand(size, e, d)
        state_half = torch.bmm(advance_t, torch.bmm(cov, advance_half))
        delta_half = torch.bmm(scatter_t, torch.bmm(delta_cov, scatter_half))
        cross = torch.bmm(advance_t, torch.bmm(cov_x_delta, scatter.expand(size, e, d)))
        return (mean @ advance, state_half + state_half.mT, delta_mean @ scatter, delta_half + delta_half.mT, cross)


class OffsetIntegration(LinearIntegration):
    """The linear step with an offset, x_{t+1} = x_t A + Δ J + b: ``offset`` b `D`, the deterministic outputs' Δ.

    The offset shifts the mean of x_{t+1} and nothing else (zero variance, zero covariance with x_t and Δ).
    """

    def __init__(self, advance: Tensor, scatter: Tensor, outputs: Sequence[int], offset: Tensor) -> None:
        super().__init__(advance, scatter, outputs)
        if offset.shape != advance.shape[-1:]:
            raise ValueError(f"offset must be `{advance.shape[0]}`, got {tuple(offset.shape)}")
        self.offset = offset

    def step(self, x: Tensor, delta: Tensor) -> Tensor:
        """x_{t+1} = x_t A + Δ J + b `... x D` from x_t `... x D` and the draws Δ of the GP's outputs `... x E'`."""
        return super().step(x, delta) + self.offset

    def for_model(self, data: dict[str, Tensor]) -> tuple[LinearIntegration, dict[str, Tensor]]:
        """A model of exactly this step's GP outputs is taken as it is, with this offset; else as the linear step."""
        if _model_outputs(data) == self.outputs:
            return self, data
        return super().for_model(data)

    def moment_terms(
        self, mean: Tensor, cov: Tensor, delta_mean: Tensor, delta_cov: Tensor, cov_x_delta: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """:meth:`LinearIntegration.moment_terms` with b added to the mean of the summand Δ J (its only change)."""
        mean, cov, delta_mean, delta_cov, cov_x_delta = super().moment_terms(mean, cov, delta_mean, delta_cov,
                                                                             cov_x_delta)
        return mean, cov, delta_mean + self.offset, delta_cov, cov_x_delta


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
        positions, velocities, period = kinematics.positions, kinematics.velocities, kinematics.period
        # a Task's are checked; one made by hand may not be
        check_kinematics(state_dim, positions, velocities, period, kinematics.weight)
        self.state_dim = state_dim
        self.period = float(period)
        outputs = tuple(d for d in range(state_dim) if d not in positions)
        column = {d: i for i, d in enumerate(outputs)}
        advance = torch.eye(state_dim, dtype=torch.float64)
        scatter = torch.zeros(len(outputs), state_dim, dtype=torch.float64)
        scatter[range(len(outputs)), list(outputs)] = 1.0
        for p, v in zip(positions, velocities, strict=True):
            advance[v, p] = self.period  # q + T q̇
            scatter[column[v], p] = kinematics.weight * self.period  # + w T Δq̇ (w = ½: the trapezoid rule)
        super().__init__(advance.to(dtype=dtype, device=device), scatter.to(dtype=dtype, device=device), outputs)


def modelled_outputs(name: str, state_dim: int, kinematics: Kinematics | None) -> tuple[int, ...]:
    """The state dimensions the GP models under integration ``name``: all (delta), or all but the positions (speed)."""
    if name == "speed" and kinematics is not None:
        return tuple(d for d in range(state_dim) if d not in kinematics.positions)
    return tuple(range(state_dim))


def _model_outputs(data: dict[str, Tensor]) -> tuple[int, ...]:
    """The state dimensions of a cache's outputs (``data["outputs"]``; 0..E−1 where it names none)."""
    if "outputs" in data:
        return tuple(int(d) for d in data["outputs"].tolist())
    return tuple(range(data["beta"].shape[-2]))


def _model_constants(data: dict[str, Tensor]) -> tuple[tuple[int, ...], Tensor | None]:
    """The state dimensions of a cache's deterministic outputs and their Δ `C` (none: ``()``, None)."""
    if "constant_outputs" not in data:
        return (), None
    return tuple(int(d) for d in data["constant_outputs"].tolist()), data["constant_delta"]


def _with_constants(
    advance: Tensor, scatter: Tensor, step_outputs: tuple[int, ...], data: dict[str, Tensor]
) -> tuple[OffsetIntegration, dict[str, Tensor]]:
    """x_{t+1} = x_t A + Δ J + b for a model with deterministic outputs, and the cache cut to its GP's outputs.

    ``scatter`` J_all `E' x D` maps each of ``step_outputs``' Δ; the GP's outputs keep their rows (J), the constant
    ones' Δ c `C` give the offset b = c J_c. Every one of ``step_outputs`` must be a GP or a constant output.
    """
    outputs = _model_outputs(data)
    constant, delta = _model_constants(data)
    if missing := [d for d in step_outputs if d not in outputs and d not in constant]:
        raise ValueError(f"the step models outputs {list(step_outputs)}, the GP outputs {list(outputs)} and "
                         f"{list(constant)} deterministically: {missing} missing")
    learned = tuple(d for d in outputs if d in step_outputs)
    fixed = [j for j, d in enumerate(constant) if d in step_outputs]
    if learned != outputs:
        data = select_outputs(data, learned)
    rows = [step_outputs.index(d) for d in learned]
    offset = delta[fixed].to(scatter) @ scatter[[step_outputs.index(constant[j]) for j in fixed]]
    return OffsetIntegration(advance, scatter[rows], learned, offset), data


def select_outputs(data: dict[str, Tensor], outputs: Sequence[int]) -> dict[str, Tensor]:
    """The cache's per-output tensors of the state dimensions ``outputs`` only (the shared inputs as they are).

    ``data``'s outputs are those its ``outputs`` entry names (0..E−1 where it names none); each of ``outputs``
    must be one of them.
    """
    held = _model_outputs(data)
    if missing := [d for d in outputs if d not in held]:
        raise ValueError(f"outputs {missing} are not among the GP's outputs {list(held)}")
    index = torch.tensor([held.index(d) for d in outputs], dtype=torch.long, device=data["beta"].device)
    output_dim = {"K_inv": -3, "prior_inv": -3, "update_root": -3, "beta": -2, "lengthscales": -2,
                  "signal_variance": -1, "noise_variance": -1, "extra_noise": -2}
    cut = {k: v.index_select(output_dim[k], index) if k in output_dim else v for k, v in data.items()}
    cut["outputs"] = torch.tensor(list(outputs), dtype=torch.long, device=data["beta"].device)
    return cut


def make_integration(
    name: str, state_dim: int, kinematics: Kinematics | None, dtype: torch.dtype, device: torch.device | str
) -> DeltaIntegration | LinearIntegration:
    """The step ``name`` (one of INTEGRATION) of a ``state_dim``-D state; ``speed`` needs ``kinematics``."""
    if name == "delta":
        return DeltaIntegration(state_dim)
    if name != "speed" or kinematics is None:
        raise ValueError(f"integration {name!r} needs to be delta, or speed with kinematics")
    return SpeedIntegration(state_dim, kinematics, dtype, device)
