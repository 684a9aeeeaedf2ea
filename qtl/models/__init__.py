"""Dynamics models: the GP of the transition function and its hyper-parameters θ."""

from qtl.models.dynamics_gp import DynamicsGP, GPPosteriorCache, exact_gp_settings
from qtl.models.hyperparameters import GPHyperparameters

__all__ = ["DynamicsGP", "GPHyperparameters", "GPPosteriorCache", "exact_gp_settings"]
