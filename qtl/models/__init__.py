"""Dynamics models: the GP of the transition function and its hyper-parameters θ."""

from qtl.models.dynamics_gp import DynamicsGP, GPPosteriorCache, exact_gp_settings
from qtl.models.hyperparameters import GPHyperparameters
from qtl.models.sparse_gp import SparseDynamicsGP

__all__ = ["DynamicsGP", "GPHyperparameters", "GPPosteriorCache", "SparseDynamicsGP", "exact_gp_settings"]
