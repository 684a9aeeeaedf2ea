"""Which code computes the moments and the exp sums: one frozen value, resolved once from ``kernels.*`` and passed down.

Every formulation computes the same exact quantities; they differ in the order of floating-point
operations, so a run's ``metrics.csv`` is reproduced exactly by the same seed *and* engine (policy
search amplifies round-off). ``moments``: ``reference`` is the plain torch formulation; ``fused``
dispatches ~45% fewer torch operations per rollout step (constant linear maps instead of gathers and
block assembly, one Cholesky factorisation per call with a closed-form backward, no redundant
symmetrizing); ``native`` is the fused formulation with its hot pieces (SE-kernel moments, angle
features, sine squashing, the RBF network at points) each one compiled call forward and one backward
(`qtl/kernels/native/`, float64 on the CPU; other dtypes and devices take the fused torch code).
``exp_sums``: ``native`` computes the weighted exp sums and the pathwise functions by the compiled
kernels (CPU), ``torch`` by plain torch. ``DEFAULT_ENGINE`` (``Engine()``) is what a caller that passes no
engine gets (torch exp sums, reference moments); :meth:`Engine.resolve` turns the config's ``kernels.*``
(``auto`` included) into one, in ``qtl.build``.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
from dataclasses import dataclass

from qtl.errors import UserError

logger = logging.getLogger(__name__)

EXP_SUMS = ("native", "torch")
EXP_SUM_CHOICES = ("auto", *EXP_SUMS)
FORMULATIONS = ("reference", "fused", "native")
MOMENT_CHOICES = (*FORMULATIONS, "auto")
NETWORK_FORMS = ("auto", "fused", "reference")
BUILD_COMMAND = "python -m qtl.kernels.native.build"


@dataclass(frozen=True)
class Engine:
    """The code that runs: ``exp_sums`` (``native`` | ``torch``), ``moments`` (``reference`` | ``fused`` | ``native``).

    ``network``: how ``RBFNetwork.forward`` computes a batch of points (``auto``: by ``moments``, the plain
    form under ``reference``, the fused op under ``fused``, its compiled twin under ``native``; ``fused``:
    the fused op even under ``native``; ``reference``: the plain form always; tests and benchmarks of the
    twins). ``lower_pairs``: the native SE moments sum the a = b pairs from their lower triangles (False:
    every pair's full n x n sum, the form before; tests and benchmarks).
    """

    exp_sums: str = "torch"
    moments: str = "reference"
    network: str = "auto"
    lower_pairs: bool = True

    def __post_init__(self) -> None:
        for name, value, allowed in (("exp_sums", self.exp_sums, EXP_SUMS), ("moments", self.moments, FORMULATIONS),
                                     ("network", self.network, NETWORK_FORMS)):
            if value not in allowed:
                raise ValueError(f"Engine.{name} must be one of {', '.join(allowed)}, got {value!r}")

    @property
    def fused(self) -> bool:
        """Whether the fused formulation runs (``native`` is the fused formulation, compiled)."""
        return self.moments != "reference"

    @property
    def native(self) -> bool:
        """Whether the native twins of the fused formulation's pieces run (float64 CPU operands)."""
        return self.moments == "native"

    def replace(self, **changes: str | bool) -> Engine:
        """This engine with ``changes`` (field names as keywords)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def resolve(cls, exp_sums: str = "auto", moments: str = "auto") -> Engine:
        """The engine of ``kernels.backend`` and ``kernels.moments``, each ``auto`` resolved; checked before any work.

        ``native`` needs the compiled library: a UserError saying how to build it when it cannot load;
        ``auto`` then takes ``torch`` (exp sums) and ``fused`` (moments), with one log line each (once per
        process) that says why.
        """
        if exp_sums not in EXP_SUM_CHOICES:
            raise UserError(f"kernels.backend must be one of {', '.join(EXP_SUM_CHOICES)}, got {exp_sums!r}")
        if exp_sums != "torch":
            exp_sums = _native_or(
                exp_sums == "native", "torch",
                "kernels.backend=native, but the native exp-sum kernel cannot load ({err}): "
                "build it with `{build}`, or choose kernels.backend=auto or torch",
                "native exp-sum kernel unavailable (%s); using the torch path (build it: `%s`)",
            )
        if moments not in MOMENT_CHOICES:
            raise UserError(f"kernels.moments must be one of {', '.join(MOMENT_CHOICES)}, got {moments!r}")
        if moments in ("native", "auto"):
            moments = _native_or(
                moments == "native", "fused",
                "kernels.moments=native, but the native kernels cannot load ({err}): "
                "build them with `{build}`, or choose kernels.moments=fused",
                "native moment kernels unavailable (%s); using kernels.moments=fused (build: `%s`)",
            )
        return cls(exp_sums=exp_sums, moments=moments)


# What a caller that passes no engine gets: the library's own default (torch exp sums, reference moments).
DEFAULT_ENGINE = Engine()


def native_build_error() -> ImportError | None:
    """Why the compiled kernels cannot load, or None when they do."""
    from qtl.kernels.native.exp_sum import load_exp_sum  # the compiled kernels sit below the engine's choice

    try:
        load_exp_sum()
    except ImportError as err:
        return err
    return None


@functools.cache
def _log_once(message: str, reason: str) -> None:
    """Log ``message`` (with ``reason`` and the build command) once per process for each message and reason."""
    logger.info(message, reason, BUILD_COMMAND)


def _native_or(required: bool, fallback: str, refusal: str, fallback_note: str) -> str:
    """``native`` when the compiled kernels load; else a UserError (``required``) or ``fallback`` with one log line."""
    err = native_build_error()
    if err is None:
        return "native"
    if required:
        raise UserError(refusal.format(err=err, build=BUILD_COMMAND)) from err
    _log_once(fallback_note, str(err))
    return fallback
