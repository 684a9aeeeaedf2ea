"""Shared kernel maths: SE-kernel moments at Gaussian inputs (gp0/gp2), their fused exp sums, GP predictive terms."""

from qtl.kernels.exp_sum import active_backend, backend, use_backend, weighted_exp_sum
from qtl.kernels.gp_predictive import gp_predictive
from qtl.kernels.moments import SEKernelMoments

__all__ = ["SEKernelMoments", "active_backend", "backend", "gp_predictive", "use_backend", "weighted_exp_sum"]
