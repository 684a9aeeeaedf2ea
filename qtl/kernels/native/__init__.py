"""Compiled CPU kernels (plain C through ctypes, compiled on first use into the per-user cache), a module per source."""

from qtl.kernels.native.artefact import artefact_path
from qtl.kernels.native.exp_sum import ExpSumLibrary, NativeWeightedExpSum, load_exp_sum
from qtl.kernels.native.first_use import library_path
from qtl.kernels.native.loader import binding_once, load_binding, open_library

__all__ = [
    "ExpSumLibrary",
    "NativeWeightedExpSum",
    "artefact_path",
    "binding_once",
    "library_path",
    "load_binding",
    "load_exp_sum",
    "open_library",
]
