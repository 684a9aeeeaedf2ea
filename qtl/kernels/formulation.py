"""Which formulation of the moment-matching maths runs: the plain reference, the fused one, or its native twin.

Both compute the same exact moments (angle features, SE-kernel moments, sine squashing, one
rollout step) and agree to ~1e-13 relative in values and gradients; they differ in the order of
floating-point operations, so a run's ``metrics.csv`` is reproduced exactly by the same seed *and*
formulation (policy search amplifies round-off, as with ``kernels.backend``). ``reference`` is the
plain torch formulation; ``fused`` dispatches ~45% fewer torch operations per rollout step
(forward and backward): constant linear maps instead of gathers and block assembly, one Cholesky
factorisation per call with a closed-form backward, no redundant symmetrizing. ``native`` is the
fused formulation with its hot pieces (SE-kernel moments, angle features, sine squashing) each one
compiled call forward and one backward (`qtl/kernels/native/`, float64 on the CPU; other dtypes and
devices take the fused torch code); it needs the native build. ``auto`` is ``native`` where the build
loads and ``fused`` elsewhere (one log line says so).
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator

from qtl.errors import UserError

logger = logging.getLogger(__name__)

FORMULATIONS = ("reference", "fused", "native")
CHOICES = (*FORMULATIONS, "auto")
BUILD_COMMAND = "python -m qtl.kernels.native.build"
_ACTIVE = ["reference"]
_FALLBACK_LOGGED = [False]


def _native_build_error() -> ImportError | None:
    """Why the compiled kernels cannot load, or None when they do."""
    from qtl.kernels import native as native_kernels  # the compiled kernels sit below this switch

    try:
        native_kernels.load_exp_sum()
    except ImportError as err:
        return err
    return None


def use_formulation(name: str) -> str:
    """Make ``name`` (``reference`` | ``fused`` | ``native`` | ``auto``) the formulation in effect; returns it.

    ``native`` needs the compiled library: a UserError saying how to build it when it cannot load;
    ``auto`` then takes ``fused`` and logs it once.
    """
    if name not in CHOICES:
        raise UserError(f"kernels.moments must be one of {', '.join(CHOICES)}, got {name!r}")
    if name in ("native", "auto"):
        err = _native_build_error()
        if err is not None and name == "native":
            raise UserError(
                f"kernels.moments=native, but the native kernels cannot load ({err}): "
                f"build them with `{BUILD_COMMAND}`, or choose kernels.moments=fused"
            ) from err
        if err is not None and not _FALLBACK_LOGGED[0]:
            logger.info("native moment kernels unavailable (%s); using kernels.moments=fused (build: `%s`)",
                        err, BUILD_COMMAND)
            _FALLBACK_LOGGED[0] = True
        name = "fused" if err is not None else "native"
    _ACTIVE[0] = name
    return name


def active_formulation() -> str:
    """``reference``, ``fused`` or ``native``: the formulation moment matching uses now."""
    return _ACTIVE[0]


def fused() -> bool:
    """Whether the fused formulation is in effect (``native`` is the fused formulation, compiled)."""
    return _ACTIVE[0] != "reference"


def native() -> bool:
    """Whether the native twins of the fused formulation's pieces run (float64 CPU operands)."""
    return _ACTIVE[0] == "native"


@contextlib.contextmanager
def formulation(name: str) -> Iterator[str]:
    """``use_formulation(name)`` for the duration of a ``with`` block (yields it)."""
    previous = _ACTIVE[0]
    try:
        yield use_formulation(name)
    finally:
        _ACTIVE[0] = previous
