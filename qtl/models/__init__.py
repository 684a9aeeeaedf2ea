"""Dynamics models: the GP of the transition function and its hyper-parameters θ."""

from qtl.models.constant import OutputSplit, split_outputs
from qtl.models.dynamics_gp import DynamicsGP, GPPosteriorCache
from qtl.models.exact_settings import exact_gp_settings
from qtl.models.fitting import AutoFit, ExactFit, ModelFit, SparseFit, log_evidence
from qtl.models.hyperparameters import GPHyperparameters
from qtl.models.sparse_gp import SparseDynamicsGP
from qtl.models.warm_start import PreviousFit

__all__ = [
    "AutoFit",
    "DynamicsGP",
    "ExactFit",
    "GPHyperparameters",
    "GPPosteriorCache",
    "ModelFit",
    "OutputSplit",
    "PreviousFit",
    "SparseDynamicsGP",
    "SparseFit",
    "exact_gp_settings",
    "log_evidence",
    "split_outputs",
]
