"""Qualitative transfer (Section 4): θ_s and ψ_s from a source run, updating rules, task compliance."""

from qtl.transfer.compliance import Compliance, leave_one_out, task_compliance
from qtl.transfer.rules import Bayesian, Forgetting, Free, HyperparameterRule, NoTransfer, RuleError
from qtl.transfer.source import SourceRun, TransferError

__all__ = [
    "Bayesian",
    "Compliance",
    "Forgetting",
    "Free",
    "HyperparameterRule",
    "NoTransfer",
    "RuleError",
    "SourceRun",
    "TransferError",
    "leave_one_out",
    "task_compliance",
]
