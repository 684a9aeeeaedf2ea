"""What one episode's evidence maximisation hands to the next: θ_p, its objective and Z (``model.warm_start``)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from qtl.models.dynamics_gp import DynamicsGP
from qtl.models.hyperparameters import GPHyperparameters
from qtl.models.sparse_gp import SparseDynamicsGP

# The previous fit must have seen at least this share of the current data to start from: on the bench data
# (docs/benchmarks.md, GP section) a θ_p of 10 points left the warm fit of 60 points 0.3-1.3 nats per point
# short of the cold fit, one of 50 points at n = 100 within 1e-3, and its objective was no guide to either.
WARM_MIN_SHARE = 0.5


@dataclass(frozen=True)
class PreviousFit:
    """The last fit's θ_p, per-output objective `E` (log evidence + log prior, / n), n, Z `m x D` if sparse.

    ``outputs``: the state dimensions of θ_p's E outputs (None: 0..E−1, a fit recorded before models held them).
    """

    theta: GPHyperparameters
    objective: Tensor
    num_points: int
    inducing: Tensor | None = None
    outputs: tuple[int, ...] | None = None
    constant_outputs: tuple[int, ...] = ()  # the outputs it modelled as deterministic (a constant Δ)

    @classmethod
    def of(cls, model: DynamicsGP) -> PreviousFit:
        """What ``model`` found in its latest fit (call it before θ is replaced by a transfer rule's θ_i)."""
        if model.fit_objective is None:
            raise ValueError("the model has not been fitted: no objective to start the next fit from")
        inducing = model.inducing_points.clone() if isinstance(model, SparseDynamicsGP) else None
        return cls(model.hyperparameters, model.fit_objective.clone(), len(model.train_x), inducing, model.outputs,
                   model.constant_outputs)

    @property
    def modelled(self) -> tuple[int, ...]:
        """The state dimensions of θ_p's outputs (0..E−1 where none were recorded)."""
        return tuple(range(self.theta.num_outputs)) if self.outputs is None else self.outputs

    def speaks_for(self, num_points: int) -> bool:
        """Whether this fit saw enough of ``num_points`` (``WARM_MIN_SHARE``) for the next fit to start from it."""
        return self.num_points >= WARM_MIN_SHARE * num_points

    def to(self, dtype: torch.dtype, device: torch.device | str) -> PreviousFit:
        """The same fit on another dtype and device."""
        inducing = None if self.inducing is None else self.inducing.to(dtype=dtype, device=device)
        return PreviousFit(self.theta.to(dtype=dtype, device=device), self.objective.to(dtype=dtype, device=device),
                           self.num_points, inducing, self.outputs, self.constant_outputs)

    def state_dict(self) -> dict[str, object]:
        """Tensors and primitives on the CPU, for a checkpoint (:meth:`from_state_dict` inverts it)."""
        return {"theta": self.theta.state_dict(), "objective": self.objective.cpu(), "num_points": self.num_points,
                "inducing": None if self.inducing is None else self.inducing.cpu(),
                "outputs": None if self.outputs is None else list(self.outputs),
                "constant_outputs": list(self.constant_outputs)}

    @classmethod
    def from_state_dict(cls, state: Mapping[str, object]) -> PreviousFit:
        """Rebuild :meth:`state_dict`."""
        outputs = state.get("outputs")
        return cls(GPHyperparameters(**state["theta"]), state["objective"], int(state["num_points"]),
                   state["inducing"], None if outputs is None else tuple(int(d) for d in outputs),
                   tuple(int(d) for d in state.get("constant_outputs", ())))

    @classmethod
    def of_checkpoint(cls, checkpoint: Mapping[str, object]) -> PreviousFit | None:
        """The fit a run's checkpoint holds; None where it has none (made before ``model.warm_start``)."""
        state = checkpoint.get("previous_fit")
        return None if state is None else cls.from_state_dict(state)
