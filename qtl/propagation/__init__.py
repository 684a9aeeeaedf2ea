"""Long-term prediction: propagate a state distribution through policy and GP (Eq. 4)."""

from qtl.propagation.kernel_moments import SEKernelMoments, weighted_exp_sum
from qtl.propagation.moment_matching import MomentMatching, Rollout

__all__ = ["MomentMatching", "Rollout", "SEKernelMoments", "weighted_exp_sum"]
