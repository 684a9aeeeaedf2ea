"""Long-term prediction: propagate a state distribution through policy and GP (Eq. 4)."""

from qtl.propagation.base import DynamicsSource, PosteriorSource, Propagator, PropagatorFactory, Rollout
from qtl.propagation.moment_matching import MomentMatching
from qtl.propagation.particles import Particles

__all__ = [
    "DynamicsSource",
    "MomentMatching",
    "Particles",
    "PosteriorSource",
    "Propagator",
    "PropagatorFactory",
    "Rollout",
]
