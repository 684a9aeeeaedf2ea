"""Policies: the RBF network of Eq. 5, a linear policy, and sine squashing to the action bounds."""

from qtl.policies.base import Policy
from qtl.policies.factories import linear_policy, rbf_policy
from qtl.policies.linear import LinearPolicy
from qtl.policies.rbf import POLICY_NOISE_VARIANCE, POLICY_SIGNAL_VARIANCE, RBFPolicy
from qtl.policies.squash import SquashedPolicy, sin_squash, sin_squash_moments

__all__ = [
    "POLICY_NOISE_VARIANCE",
    "POLICY_SIGNAL_VARIANCE",
    "LinearPolicy",
    "Policy",
    "RBFPolicy",
    "SquashedPolicy",
    "linear_policy",
    "rbf_policy",
    "sin_squash",
    "sin_squash_moments",
]
