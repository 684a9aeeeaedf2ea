"""Build qtl's native kernels (one shared library) into the per-user cache, unless already built.

    python -m qtl.kernels.native.build [--force] [--optional] [--where]

Compiles every `*.c` of this directory (`exp_sum.c`, `se_moments.c`, `trig.c`, `pathwise.c`, `rbf_network.c`) with
`$CC` (else `gcc`) and `artefact.FLAGS` into `<cache>/native/_qtl_kernels-<key>.so` (`<cache>`: `$QTL_CACHE_DIR`,
else `$XDG_CACHE_HOME/qtl`, else `~/.cache/qtl`), the key a hash of the sources, the compiler, the flags and the CPU
(so a changed source or another machine rebuilds), then checks the exp sums, the SE-kernel moments, the
pathwise-function values and the RBF network against their torch twins on small problems before keeping it (the
angle-feature and squashing kernels of `trig.c` are compared with theirs by the test suite). One process compiles
at a time (a lock file in the cache); the others wait for it and find the library built. qtl calls :func:`build` on
first use (`first_use.library_path`); this command builds ahead of time (`scripts/setup.sh`). ``--optional`` turns
a failed build into one line saying that qtl will use the torch path; ``--where`` prints the library's path.
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

from qtl.kernels.native.artefact import (
    ARTEFACT_PREFIX,
    CACHE_ENV,
    DIRECTORY,
    FLAGS,
    LIBS,
    SOURCES,
    artefact_path,
    compiler,
)
from qtl.kernels.native.exp_sum import ExpSumLibrary, NativeWeightedExpSum, load_exp_sum
from qtl.kernels.native.loader import open_library
from qtl.kernels.native.lock import exclusive
from qtl.kernels.native.pathwise import PathValuesLibrary
from qtl.kernels.native.pathwise import check_against_torch as check_path_values
from qtl.kernels.native.rbf_network import NetworkLibrary
from qtl.kernels.native.rbf_network import check_against_torch as check_network
from qtl.kernels.native.se_moments import SEMomentsLibrary
from qtl.kernels.native.se_moments_check import check_against_torch as check_se_moments

logger = logging.getLogger(__name__)

# The smoke check's tolerance (relative, float64): the kernel agrees with torch to ~1e-15.
CHECK_RTOL = 1e-12
# Libraries that earlier set-ups built into the package directory (`_exp_sum-`: the name before), unused now.
LEGACY_PREFIXES = (ARTEFACT_PREFIX, "_exp_sum-")
LOCK_NAME = ".build.lock"


class BuildError(RuntimeError):
    """The compiler failed, or the compiled kernel disagrees with the torch twin."""


class CompilerError(BuildError):
    """The C compiler is missing or failed."""


def advice(err: BaseException) -> str:
    """What to do about a failed build: install a compiler, choose a writable cache, or report a disagreement."""
    if isinstance(err, CompilerError):
        return "install gcc, or set CC to a C compiler with OpenMP"
    if isinstance(err, OSError):
        return f"set {CACHE_ENV} to a writable directory"
    return "please report it; kernels.backend=torch kernels.moments=fused avoids the compiled code"


def compile_kernel(target: Path) -> None:
    """Compile the sources into ``target`` (atomically: a temporary file, then a rename)."""
    tmp = target.with_name(f"{target.stem}.{os.getpid()}.tmp")
    command = compiler()
    try:
        done = subprocess.run(
            [*command, *FLAGS, "-o", str(tmp), *map(str, SOURCES), *LIBS], capture_output=True, text=True, check=False
        )
    except OSError as err:
        raise CompilerError(f"cannot run {' '.join(command)}: {err}") from err
    if done.returncode != 0:
        tmp.unlink(missing_ok=True)
        first = (done.stderr.strip().splitlines() or ["no message"])[0]
        raise CompilerError(f"{' '.join(command)} failed ({first})")
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


def check_library(path: Path) -> None:
    """The library at ``path`` agrees with the torch twins (exp sums, SE moments, pathwise values, RBF network)."""
    lib = open_library(path)
    check_against_torch(ExpSumLibrary(lib))
    check_se_moments(SEMomentsLibrary(lib), error=BuildError)
    check_path_values(PathValuesLibrary(lib), error=BuildError)
    check_network(NetworkLibrary(lib), error=BuildError)


def build(force: bool = False) -> Path:
    """The library for these sources, compiler, flags and CPU: compiled and checked unless already there.

    One process at a time compiles (a lock file beside the library); one that waited finds it built. A fresh
    library is checked under a temporary name and only then renamed into place, so no process loads an unchecked one.
    """
    target = artefact_path()
    if target.is_file() and not force:
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    with exclusive(target.parent / LOCK_NAME):
        if target.is_file() and not force:
            return target  # another process built it while this one waited
        for stale in target.parent.glob("*.unchecked.so"):  # left by a build that crashed: only the lock holder builds
            stale.unlink(missing_ok=True)
        tic = time.perf_counter()
        candidate = target.with_name(f"{target.stem}.{os.getpid()}.unchecked.so")
        try:
            compile_kernel(candidate)
            check_library(candidate)
            os.replace(candidate, target)
        finally:
            candidate.unlink(missing_ok=True)
    logger.info("compiled the native kernels into %s in %.1f s", target, time.perf_counter() - tic)
    return target


def remove_legacy_builds() -> None:
    """Delete the libraries that earlier set-ups compiled into the package directory (where it is writable)."""
    for stale in (path for prefix in LEGACY_PREFIXES for path in DIRECTORY.glob(f"{prefix}*.so")):
        try:
            stale.unlink()
        except OSError:
            pass


def main(argv: list[str] | None = None) -> int:
    """Command line: build (or keep) the library, or print its path; exit status 1 on failure unless ``--optional``."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--force", action="store_true", help="rebuild even when the cached library is there")
    parser.add_argument("--optional", action="store_true", help="a failed build prints one line and exits 0")
    parser.add_argument(
        "--where",
        action="store_true",
        help="print the library's path and build nothing (exit status 1 when it is not built yet)",
    )
    args = parser.parse_args(argv)
    if args.where:
        print(artefact_path())
        return 0 if artefact_path().is_file() else 1
    logging.basicConfig(level=logging.INFO, format="qtl: %(message)s")
    try:
        build(force=args.force)
    except (BuildError, ImportError, OSError) as err:
        print(f"qtl: native kernels not built ({err}; {advice(err)}); qtl will use the torch path", file=sys.stderr)
        return 0 if args.optional else 1
    remove_legacy_builds()
    return 0


if __name__ == "__main__":
    sys.exit(main())
