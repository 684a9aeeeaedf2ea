"""The compiled kernels on first use: the library of these sources, compiler, flags and CPU, built when missing."""

from __future__ import annotations

from pathlib import Path

from qtl.kernels.native.artefact import artefact_path

# Why a library could not be had, by its path: a process tries each build once (a compile takes seconds).
_FAILED: dict[Path, str] = {}


def library_path() -> Path:
    """The library, compiled into the per-user cache on first use; ImportError saying why and what to do when not.

    The compile logs one line; a failed one is not retried in this process (`python -m qtl.kernels.native.build`
    retries it and prints the compiler's message).
    """
    target = artefact_path()
    if target.is_file():
        return target
    if target in _FAILED:
        raise ImportError(_FAILED[target])
    from qtl.kernels.native import build  # here: the build checks the bindings, which load through this module

    try:
        return build.build()
    except (build.BuildError, OSError) as err:
        _FAILED[target] = f"{err}; {build.advice(err)}"
        raise ImportError(_FAILED[target]) from err
