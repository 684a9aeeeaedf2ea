"""One evaluation of the objective at ψ: checked finite, its failures counted; ψ copied."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from qtl import health
from qtl.errors import NonFiniteObjective

# Errors of an evaluation at a numerically invalid ψ: they end a run (sequential) or drop a restart (batched).
INVALID_PSI_ERRORS = (NonFiniteObjective, torch.linalg.LinAlgError)


def count_failure(err: BaseException) -> None:
    """Count an evaluation that failed: a non-finite value or gradient, or a failed factorisation."""
    health.count(health.NONFINITE if isinstance(err, NonFiniteObjective) else health.LINALG)


def checked(value: Tensor) -> Tensor:
    """``value`` itself; :class:`~qtl.errors.NonFiniteObjective` where it is not finite."""
    if not torch.isfinite(value).all():
        raise NonFiniteObjective(f"predicted return is {value.item()}")
    return value


def state(policy: nn.Module) -> dict[str, Tensor]:
    """A copy of ``policy``'s ψ."""
    return {k: v.detach().clone() for k, v in policy.state_dict().items()}
