"""Long-term prediction: propagate a state distribution through policy and GP (Eq. 4)."""

from qtl.propagation.moment_matching import MomentMatching, Rollout
from qtl.propagation.particles import Particles

__all__ = ["MomentMatching", "Particles", "Rollout"]
