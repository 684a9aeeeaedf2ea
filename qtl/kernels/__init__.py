"""Shared kernel maths: SE-kernel moments at Gaussian inputs (gp0/gp2), their fused exp sums, GP predictive terms."""

from qtl.kernels.engine import Engine
from qtl.kernels.exp_sum import weighted_exp_sum
from qtl.kernels.gp_predictive import gp_predictive
from qtl.kernels.moments import SEKernelMoments

__all__ = ["Engine", "SEKernelMoments", "gp_predictive", "weighted_exp_sum"]
