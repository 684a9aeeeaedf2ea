"""Outputs whose Δ never changes (a contact force that stays 0, a fixed target, a flag): deterministic, not a GP.

A GP of a constant Δ has no scale to learn: its heuristic noise falls below the noise floor and evidence
maximisation has nothing to fit. Such an output is detected from the data at each fit by :func:`constant_columns`
and modelled as deterministic, its Δ the data's mean with zero variance and zero covariance; the step
x_{t+1} = x_t A + Δ J + b then carries it in its offset b (:mod:`qtl.propagation.integration`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from torch import Tensor

# An output's Δ is constant when its standard deviation over the data is at most
# CONSTANT_DELTA_ATOL + CONSTANT_DELTA_RTOL · |mean Δ|: the absolute part catches the zero Δ of a value that never
# moves (far below any physical spread, far above float64 round-off of values up to ~1e6), the relative part the
# round-off of a Δ that is the same non-zero amount each step (a clock).
CONSTANT_DELTA_ATOL = 1e-9
CONSTANT_DELTA_RTOL = 1e-6


def constant_columns(targets: Tensor) -> Tensor:
    """Which columns of the targets Δ `n x E` are constant (the criterion above): a boolean `E`."""
    std = targets.std(dim=0, correction=0)
    return std <= CONSTANT_DELTA_ATOL + CONSTANT_DELTA_RTOL * targets.mean(dim=0).abs()


@dataclass(frozen=True)
class OutputSplit:
    """The modelled outputs of a fit split into those a GP learns and the constant ones.

    ``varying``: the columns `E''` of the targets the GP learns; ``outputs``: their state dimensions;
    ``constant_outputs``: the state dimensions of the constant columns; ``constant_delta``: their mean Δ `C`.
    """

    varying: list[int]
    outputs: tuple[int, ...]
    constant_outputs: tuple[int, ...]
    constant_delta: Tensor


def split_outputs(targets: Tensor, outputs: Sequence[int] | None = None) -> OutputSplit:
    """The targets `n x E` of the state dimensions ``outputs`` (default 0..E−1) split by :func:`constant_columns`.

    Every output constant leaves nothing to learn: a ValueError naming them.
    """
    dims = tuple(range(targets.shape[-1])) if outputs is None else tuple(int(d) for d in outputs)
    constant = constant_columns(targets).tolist()
    if all(constant):
        raise ValueError(f"the Δ of every modelled output {list(dims)} is constant in the data: no dynamics to learn "
                         "(does the action reach the env?)")
    varying = [j for j, c in enumerate(constant) if not c]
    fixed = [j for j, c in enumerate(constant) if c]
    return OutputSplit(varying, tuple(dims[j] for j in varying), tuple(dims[j] for j in fixed),
                       targets[:, fixed].mean(dim=0))
