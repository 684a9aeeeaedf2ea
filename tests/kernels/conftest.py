"""Shared fixtures of the kernel tests: the native kernel, built once."""

from __future__ import annotations

from pathlib import Path

import pytest

from qtl.kernels.native import build as native_build


@pytest.fixture(scope="module")
def built() -> Path:
    """The native kernel, built (or found in the cache); skipped where no compiler is found."""
    try:
        return native_build.build()
    except native_build.BuildError as err:
        if "cannot run" in str(err):
            pytest.skip(f"no C compiler: {err}")
        raise
