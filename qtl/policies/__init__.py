"""Policies: RBF networks (Eq. 5: PILCO's, or free weights with dropout), linear; sine squashing; restarts batched."""

from qtl.policies.base import Policy
from qtl.policies.batching import batched_policy, psi_names, restart_state, set_psi, stack_psi
from qtl.policies.factories import linear_policy, rbf_network_policy, rbf_policy
from qtl.policies.linear import LinearPolicy
from qtl.policies.rbf import POLICY_NOISE_VARIANCE, POLICY_SIGNAL_VARIANCE, RBFPolicy
from qtl.policies.rbf_network import RBFNetwork
from qtl.policies.squash import SquashedPolicy, sin_squash, sin_squash_moments

__all__ = [
    "POLICY_NOISE_VARIANCE",
    "POLICY_SIGNAL_VARIANCE",
    "LinearPolicy",
    "Policy",
    "RBFNetwork",
    "RBFPolicy",
    "SquashedPolicy",
    "batched_policy",
    "linear_policy",
    "psi_names",
    "rbf_network_policy",
    "rbf_policy",
    "restart_state",
    "set_psi",
    "sin_squash",
    "sin_squash_moments",
    "stack_psi",
]
