"""Every error type qtl raises on purpose, in one place below everything that raises them.

:class:`UserError` and its subclasses are bad input: the message is one line that says what
to fix, and the CLI prints it as that line (the traceback only with ``hydra.verbose``).
The others are numerical events a caller recovers from.
"""

from __future__ import annotations


class UserError(ValueError):
    """Bad input found before (or instead of) any work; the message says what to fix."""


class TaskError(UserError):
    """A task configuration that cannot work; the message says what to fix."""


class CheckpointError(UserError):
    """A run directory or checkpoint that cannot be resumed from; the message says why."""


class RuleError(UserError):
    """A rule's setting is invalid (e.g. γ outside [0, 1]); the message names it."""


class TransferError(UserError):
    """A source run that cannot be transferred to this target, or an inconsistent transfer config."""


class RunMismatch(RuntimeError):
    """A run directory exists but was made by other overrides."""


class NonFiniteObjective(RuntimeError):
    """The predicted return or its gradient was NaN or inf; the step that produced it is rejected."""
