"""Which formulation of the moment-matching maths runs: the plain reference or the fused one.

Both compute the same exact moments (angle features, SE-kernel moments, sine squashing, one
rollout step) and agree to ~1e-13 relative in values and gradients; they differ in the order of
floating-point operations, so a run's ``metrics.csv`` is reproduced exactly by the same seed *and*
formulation (policy search amplifies round-off, as with ``kernels.backend``). ``reference`` is the
plain torch formulation; ``fused`` dispatches ~45% fewer torch operations per rollout step
(forward and backward): constant linear maps instead of gathers and block assembly, one Cholesky
factorisation per call with a closed-form backward, no redundant symmetrizing.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

from qtl.errors import UserError

FORMULATIONS = ("reference", "fused")
_ACTIVE = ["reference"]


def use_formulation(name: str) -> str:
    """Make ``name`` (``reference`` | ``fused``) the formulation in effect; returns it."""
    if name not in FORMULATIONS:
        raise UserError(f"kernels.moments must be one of {', '.join(FORMULATIONS)}, got {name!r}")
    _ACTIVE[0] = name
    return name


def active_formulation() -> str:
    """``reference`` or ``fused``: the formulation moment matching uses now."""
    return _ACTIVE[0]


def fused() -> bool:
    """Whether the fused formulation is in effect."""
    return _ACTIVE[0] == "fused"


@contextlib.contextmanager
def formulation(name: str) -> Iterator[str]:
    """``use_formulation(name)`` for the duration of a ``with`` block (yields it)."""
    previous = _ACTIVE[0]
    try:
        yield use_formulation(name)
    finally:
        _ACTIVE[0] = previous
