"""Qualitative transfer (Section 4): θ_s and ψ_s from a source run, updating rules, task compliance."""

from qtl.errors import RuleError, TransferError
from qtl.transfer.compliance import (
    Compliance,
    KernelCompliance,
    compliance_function,
    compliance_value,
    kernel_compliance,
    leave_one_out,
    scott_bandwidth,
    task_compliance,
)
from qtl.transfer.rules import Bayesian, Forgetting, Free, HyperparameterRule, NoTransfer
from qtl.transfer.source import SourceRun

__all__ = [
    "Bayesian",
    "Compliance",
    "Forgetting",
    "Free",
    "HyperparameterRule",
    "KernelCompliance",
    "NoTransfer",
    "RuleError",
    "SourceRun",
    "TransferError",
    "compliance_function",
    "compliance_value",
    "kernel_compliance",
    "leave_one_out",
    "scott_bandwidth",
    "task_compliance",
]
