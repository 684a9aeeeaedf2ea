"""Shared kernel maths: SE-kernel moments at Gaussian inputs (gp0/gp2) and the fused exp sums under them."""

from qtl.kernels.exp_sum import weighted_exp_sum
from qtl.kernels.moments import SEKernelMoments

__all__ = ["SEKernelMoments", "weighted_exp_sum"]
