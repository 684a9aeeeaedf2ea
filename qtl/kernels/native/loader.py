"""The one shared library of the compiled kernels, opened once through ctypes; each binding declares its symbols."""

from __future__ import annotations

import ctypes
import functools
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import torch  # noqa: F401  (first: the library then shares the libgomp torch has loaded)

from qtl.kernels.native.first_use import library_path

Binding = TypeVar("Binding")


def open_library(path: Path) -> ctypes.CDLL:
    """The shared library at ``path``, opened through ctypes (the one place that opens it)."""
    return ctypes.CDLL(str(path))


@functools.cache
def _opened(path: Path) -> ctypes.CDLL:
    """:func:`open_library`, once per path."""
    return open_library(path)


@functools.cache
def _bound(binding: Callable[[ctypes.CDLL], Binding], path: Path) -> Binding:
    """``binding`` over the library at ``path``, once per (binding, path)."""
    return binding(_opened(path))


def load_binding(binding: Callable[[ctypes.CDLL], Binding]) -> Binding:
    """``binding`` (a ctypes wrapper of some of its symbols) over the library built for these sources, flags and CPU.

    Compiled on first use (:func:`library_path`), opened once per path, bound once per (binding, path); an
    ImportError saying why when the library cannot be built, does not load or lacks the symbols.
    """
    path = library_path()
    try:
        return _bound(binding, path)
    except (OSError, AttributeError) as err:
        raise ImportError(f"{path.name} does not load: {err}") from err


@functools.cache
def binding_once(binding: Callable[[ctypes.CDLL], Binding]) -> Binding:
    """:func:`load_binding`, once per process for hot paths (finding the library hashes the sources)."""
    return load_binding(binding)
