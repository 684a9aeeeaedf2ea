"""The compiled kernels on first use: the library of these sources, compiler, flags and CPU, built when missing.

The build runs as its own process (``python -m qtl.kernels.native.build``): it compiles, checks the library against
the torch twins (which sit above the bindings), and takes the cache's lock, so that of several processes starting at
once one compiles and the others wait. Its one line ("compiled the native kernels into ...") is logged here.
"""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

from qtl.kernels.native.artefact import artefact_path

BUILD_MODULE = "qtl.kernels.native.build"
PREFIX = "qtl: "  # of the build command's lines
log = logging.getLogger(__name__)

# Why a library could not be had, by its path: a process tries each build once (a compile takes seconds).
_FAILED: dict[Path, str] = {}


def library_path() -> Path:
    """The library, compiled into the per-user cache on first use; ImportError saying why and what to do when not.

    The compile logs one line; a failed one is not retried in this process (``python -m qtl.kernels.native.build``
    retries it and prints the compiler's message).
    """
    target = artefact_path()
    if target.is_file():
        return target
    if target in _FAILED:
        raise ImportError(_FAILED[target])
    done = subprocess.run([sys.executable, "-m", BUILD_MODULE], capture_output=True, text=True, check=False)
    lines = [line.removeprefix(PREFIX) for line in done.stderr.splitlines() if line.strip()]
    if done.returncode == 0 and target.is_file():
        for line in lines:
            if line.startswith("compiled the native kernels"):
                log.info("%s", line)
        return target
    _FAILED[target] = lines[-1] if lines else f"{BUILD_MODULE} exited with status {done.returncode}"
    raise ImportError(_FAILED[target])
