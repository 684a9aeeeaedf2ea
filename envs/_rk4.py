"""The fixed-step RK4 integrator of the continuous-time environments (plain floats for speed).

Each control period `dt` holds the action (zero-order hold) and is split into equal sub-steps no
longer than the env's `integrator_dt`; small state vectors are integrated as lists of floats, as
numpy's per-call overhead dominates at these sizes.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import TypeVar

U = TypeVar("U")

# Relative slack when dividing dt into sub-steps, so 0.1 / 0.01 gives 10 and not 11.
_SUBSTEP_ROUNDING_SLACK = 1e-9


def n_substeps(dt: float, integrator_dt: float) -> int:
    """Number of equal RK4 sub-steps, ceil(`dt` / `integrator_dt`), at least 1."""
    return max(1, math.ceil(dt / integrator_dt - _SUBSTEP_ROUNDING_SLACK))


def rk4_step(
    derivative: Callable[[Sequence[float], U], Sequence[float]],
    s: Sequence[float],
    h: float,
    u: U,
) -> list[float]:
    """One classical RK4 step of length `h` from state `s` under the held input `u`."""
    k1 = derivative(s, u)
    k2 = derivative([a + 0.5 * h * k for a, k in zip(s, k1, strict=True)], u)
    k3 = derivative([a + 0.5 * h * k for a, k in zip(s, k2, strict=True)], u)
    k4 = derivative([a + h * k for a, k in zip(s, k3, strict=True)], u)
    return [a + h / 6.0 * (b + 2.0 * c + 2.0 * d + e) for a, b, c, d, e in zip(s, k1, k2, k3, k4, strict=True)]
