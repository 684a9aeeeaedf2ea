"""Compiled CPU kernels (plain C through ctypes, built by `python -m qtl.kernels.native.build`)."""

from qtl.kernels.native.artefact import artefact_path
from qtl.kernels.native.exp_sum import NativeWeightedExpSum
from qtl.kernels.native.library import ExpSumLibrary, load_exp_sum

__all__ = ["ExpSumLibrary", "NativeWeightedExpSum", "artefact_path", "load_exp_sum"]
