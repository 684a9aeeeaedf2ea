"""Declarative saturating reward shared by the environments and the learner (Eq. 13)."""

from __future__ import annotations

import operator
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


def augment_angles(x: np.ndarray, angle_dims: Sequence[int]) -> np.ndarray:
    """Map a state `... x D` to `... x (D + len(angle_dims))`: non-angle dims, then (sin, cos) per angle.

    This is the one convention of the project for angle features: the raw angle is dropped and
    ``sin θ_a, cos θ_a`` are appended, in the order of ``angle_dims``.
    """
    x = np.asarray(x, dtype=float)
    dim = x.shape[-1]
    angles = set(angle_dims)
    keep = [i for i in range(dim) if i not in angles]
    parts = [x[..., keep]]
    for a in angle_dims:
        parts.append(np.stack([np.sin(x[..., a]), np.cos(x[..., a])], axis=-1))
    return np.concatenate(parts, axis=-1)


@dataclass(frozen=True)
class SaturatingReward:
    """r(x) = exp(-½ (y - y*)ᵀ W (y - y*) / width²), y the angle-augmented state (Eq. 13).

    ``target`` (y*) and ``weight`` (W) live in the augmented coordinates of
    :func:`augment_angles` with ``angle_dims``; ``state_dim`` is the raw state dimension D.
    ``target`` and ``weight`` may be given as numpy arrays or (nested) sequences: they are stored
    as tuples of floats (and ``angle_dims`` as a tuple of ints), so a spec is immutable, hashable
    and compares by value.
    """

    state_dim: int
    angle_dims: tuple[int, ...]
    target: tuple[float, ...]
    weight: tuple[tuple[float, ...], ...]
    width: float

    def __post_init__(self) -> None:
        angle_dims = tuple(operator.index(a) for a in self.angle_dims)
        aug = self.state_dim + len(angle_dims)
        if any(not 0 <= a < self.state_dim for a in angle_dims):
            raise ValueError(f"angle_dims {angle_dims} out of range for state_dim {self.state_dim}")
        t = np.asarray(self.target, dtype=float)
        if t.shape != (aug,):
            raise ValueError(f"target has shape {t.shape}, augmented state has length {aug}")
        w = np.asarray(self.weight, dtype=float)
        if w.shape != (aug, aug):
            raise ValueError(f"weight has shape {w.shape}, expected ({aug}, {aug})")
        if not np.allclose(w, w.T) or np.linalg.eigvalsh(w).min() < -1e-12:
            raise ValueError("weight must be symmetric positive semi-definite")
        if not self.width > 0:
            raise ValueError(f"width must be positive, got {self.width}")
        # Frozen dataclass: store the normalised fields behind the generated __setattr__.
        object.__setattr__(self, "angle_dims", angle_dims)
        object.__setattr__(self, "target", tuple(t.tolist()))
        object.__setattr__(self, "weight", tuple(tuple(row) for row in w.tolist()))

    @property
    def weight_matrix(self) -> np.ndarray:
        """W / width², the matrix the quadratic form actually uses."""
        return np.asarray(self.weight, dtype=float) / self.width**2

    def __call__(self, x: np.ndarray) -> np.ndarray | float:
        """Reward of a raw state `... x D`."""
        y = augment_angles(x, self.angle_dims) - np.asarray(self.target, dtype=float)
        r = np.exp(-0.5 * np.einsum("...i,ij,...j->...", y, self.weight_matrix, y))
        return float(r) if np.ndim(r) == 0 else r
