"""Build qtl's native kernels (one shared library) into this package directory, unless already built (cached).

    python -m qtl.kernels.native.build [--force] [--optional]

Compiles every `*.c` of this directory (`exp_sum.c`, `se_moments.c`, `trig.c`, `pathwise.c`, `rbf_network.c`) with
`artefact.COMPILER` and `artefact.FLAGS` into `_qtl_kernels-<key>.so`, the key a hash of the sources, the flags
and the CPU (so a changed source or another machine rebuilds), then checks the exp sums, the SE-kernel
moments, the pathwise-function values and the RBF network against their torch twins on small problems before keeping it
(the angle-feature and squashing kernels of `trig.c` are compared with theirs by the test suite). ``--optional`` (used
by `scripts/setup.sh`) turns a failed build into one line saying that qtl will use the torch path.
"""

from __future__ import annotations

import argparse
import logging
import os
import subprocess
import sys
import time
from pathlib import Path

import torch

from qtl.kernels.native.artefact import ARTEFACT_PREFIX, COMPILER, FLAGS, LIBS, SOURCES, artefact_path
from qtl.kernels.native.exp_sum import ExpSumLibrary, NativeWeightedExpSum, load_exp_sum
from qtl.kernels.native.loader import open_library
from qtl.kernels.native.pathwise import PathValuesLibrary
from qtl.kernels.native.pathwise import check_against_torch as check_path_values
from qtl.kernels.native.rbf_network import NetworkLibrary
from qtl.kernels.native.rbf_network import check_against_torch as check_network
from qtl.kernels.native.se_moments import SEMomentsLibrary
from qtl.kernels.native.se_moments_check import check_against_torch as check_se_moments

logger = logging.getLogger(__name__)

# The smoke check's tolerance (relative, float64): the kernel agrees with torch to ~1e-15.
CHECK_RTOL = 1e-12
# Libraries of other sources, flags or CPUs, removed once a build succeeds (`_exp_sum-`: the name before).
STALE_PREFIXES = (ARTEFACT_PREFIX, "_exp_sum-")


class BuildError(RuntimeError):
    """The compiler failed, or the compiled kernel disagrees with the torch twin."""


def compile_kernel(target: Path) -> None:
    """Compile the sources into ``target`` (atomically: a temporary file, then a rename)."""
    tmp = target.with_name(f"{target.stem}.{os.getpid()}.tmp")
    cmd = [COMPILER, *FLAGS, "-o", str(tmp), *map(str, SOURCES), *LIBS]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    except OSError as err:
        raise BuildError(f"cannot run {COMPILER}: {err}") from err
    if done.returncode != 0:
        tmp.unlink(missing_ok=True)
        first = (done.stderr.strip().splitlines() or ["no message"])[0]
        raise BuildError(f"{COMPILER} failed ({first})")
    os.replace(tmp, target)


def check_against_torch(library: ExpSumLibrary | None = None) -> None:
    """The kernel's value and gradients equal the plain torch formula on a small odd-shaped problem.

    A and B `2 x 3 x n x K`, W `3 x n x m` broadcast over the leading dimension (as for restarts);
    once with W needing a gradient (backward recomputes) and once without (forward forms G_A, G_B).
    ``library``: the kernel to check (default: the one built for this source and CPU).
    """
    library = library or load_exp_sum()
    gen = torch.Generator().manual_seed(0)
    a = (0.3 * torch.randn(2, 3, 37, 5, generator=gen, dtype=torch.float64)).requires_grad_()
    b = (0.3 * torch.randn(2, 3, 41, 5, generator=gen, dtype=torch.float64)).requires_grad_()
    w = torch.rand(3, 37, 41, generator=gen, dtype=torch.float64)
    for operands in ((a, b, w.requires_grad_()), (a, b, w.detach())):
        wanted = tuple(t for t in operands if t.requires_grad)
        native = NativeWeightedExpSum.apply(a, b, operands[2].expand(2, -1, -1, -1), library, True)
        reference = (operands[2] * torch.exp(a @ b.mT)).sum((-2, -1))
        for got, want in zip(
            (native, *torch.autograd.grad(native.sum(), wanted)),
            (reference, *torch.autograd.grad(reference.sum(), wanted)),
            strict=True,
        ):
            if not torch.allclose(got, want, rtol=CHECK_RTOL, atol=0.0):
                raise BuildError(f"the compiled kernel disagrees with torch (max error {(got - want).abs().max():.3g})")


def build(force: bool = False) -> Path:
    """The library for these sources, flags and CPU: compiled and checked unless already there."""
    target = artefact_path()
    if target.is_file() and not force:
        logger.debug("native kernels up to date: %s", target)
        return target
    tic = time.perf_counter()
    compile_kernel(target)
    try:
        lib = open_library(target)
        check_against_torch(ExpSumLibrary(lib))
        check_se_moments(SEMomentsLibrary(lib), error=BuildError)
        check_path_values(PathValuesLibrary(lib), error=BuildError)
        check_network(NetworkLibrary(lib), error=BuildError)
    except BaseException:
        target.unlink(missing_ok=True)
        raise
    for stale in (path for prefix in STALE_PREFIXES for path in target.parent.glob(f"{prefix}*.so")):
        if stale != target:
            stale.unlink(missing_ok=True)
    logger.info("built the native kernels %s in %.1f s", target, time.perf_counter() - tic)
    return target


def main(argv: list[str] | None = None) -> int:
    """Command line: build (or keep) the library; exit status 1 on failure unless ``--optional``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--force", action="store_true", help="rebuild even when the cached library is there")
    parser.add_argument("--optional", action="store_true", help="a failed build prints one line and exits 0")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="qtl: %(message)s")
    try:
        build(force=args.force)
    except (BuildError, ImportError, OSError) as err:
        print(f"qtl: native kernels not built ({err}); qtl will use the torch path", file=sys.stderr)
        return 0 if args.optional else 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
