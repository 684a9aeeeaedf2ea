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

    def describe(self) -> str:
        """What a run's log says of its kernels: ``native (<library path>)`` when compiled code runs, else ``torch``."""
        if "native" not in (self.exp_sums, self.moments):
            return "torch"
        from qtl.kernels.native.artefact import artefact_path  # where the resolved engine's library is (built by now)

        return f"native ({artefact_path()})"

    def replace(self, **changes: str | bool) -> Engine:
        """This engine with ``changes`` (field names as keywords)."""
        return dataclasses.replace(self, **changes)

    @classmethod
    def resolve(cls, exp_sums: str = "auto", moments: str = "auto") -> Engine:
        """The engine of ``kernels.backend`` and ``kernels.moments``, each ``auto`` resolved; checked before any work.

        ``native`` needs the compiled library (compiled on first use): a UserError saying why when it cannot be had;
        ``auto`` then takes ``torch`` (exp sums) and ``fused`` (moments), with one log line (once per process) that
        says why and what it uses instead.
        """
        if exp_sums not in EXP_SUM_CHOICES:
            raise UserError(f"kernels.backend must be one of {', '.join(EXP_SUM_CHOICES)}, got {exp_sums!r}")
        if moments not in MOMENT_CHOICES:
            raise UserError(f"kernels.moments must be one of {', '.join(MOMENT_CHOICES)}, got {moments!r}")
        wants_native = exp_sums != "torch" or moments in ("native", "auto")
        err = native_build_error() if wants_native else None
        if err is not None and exp_sums == "native":
            raise UserError(
                f"kernels.backend=native, but the native exp-sum kernel cannot load ({err}): "
                f"build it with `{BUILD_COMMAND}`, or choose kernels.backend=auto or torch"
            ) from err
        if err is not None and moments == "native":
            raise UserError(
                f"kernels.moments=native, but the native kernels cannot load ({err}): "
                f"build them with `{BUILD_COMMAND}`, or choose kernels.moments=fused"
            ) from err
        fallbacks = []
        if moments == "auto":
            moments = "fused" if err is not None else "native"
            fallbacks.append("kernels.moments=fused")
        if exp_sums == "auto":
            exp_sums = "torch" if err is not None else "native"
            fallbacks.append("kernels.backend=torch")
        if err is not None and fallbacks:
            _log_once(" and ".join(fallbacks), str(err))
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
def _log_once(fallbacks: str, reason: str) -> None:
    """Say once per process (for each choice and reason) that the native kernels are not used, why and instead what."""
    logger.info("native kernels unavailable (%s); using %s (`%s` retries the build and says why it fails)",
                reason, fallbacks, BUILD_COMMAND)
