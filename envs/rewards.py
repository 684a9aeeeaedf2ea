"""Declarative saturating reward shared by the environments and the learner (Eq. 13)."""

from __future__ import annotations

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
    keep = [i for i in range(dim) if i not in set(angle_dims)]
    parts = [x[..., keep]]
    for a in angle_dims:
        parts.append(np.stack([np.sin(x[..., a]), np.cos(x[..., a])], axis=-1))
    return np.concatenate(parts, axis=-1)


@dataclass(frozen=True)
class SaturatingReward:
    """r(x) = exp(-½ (y - y*)ᵀ W (y - y*) / width²), y the angle-augmented state (Eq. 13).

    ``target`` (y*) and ``weight`` (W) live in the augmented coordinates of
    :func:`augment_angles` with ``angle_dims``; ``state_dim`` is the raw state dimension D.
    """

    state_dim: int
    angle_dims: tuple[int, ...]
    target: tuple[float, ...]
    weight: tuple[tuple[float, ...], ...]
    width: float

    def __post_init__(self) -> None:
        aug = self.state_dim + len(self.angle_dims)
        if any(not 0 <= a < self.state_dim for a in self.angle_dims):
            raise ValueError(f"angle_dims {self.angle_dims} out of range for state_dim {self.state_dim}")
        if len(self.target) != aug:
            raise ValueError(f"target has length {len(self.target)}, augmented state has {aug}")
        w = np.asarray(self.weight, dtype=float)
        if w.shape != (aug, aug):
            raise ValueError(f"weight has shape {w.shape}, expected ({aug}, {aug})")
        if not np.allclose(w, w.T) or np.linalg.eigvalsh(w).min() < -1e-12:
            raise ValueError("weight must be symmetric positive semi-definite")
        if not self.width > 0:
            raise ValueError(f"width must be positive, got {self.width}")

    @property
    def weight_matrix(self) -> np.ndarray:
        """W / width², the matrix the quadratic form actually uses."""
        return np.asarray(self.weight, dtype=float) / self.width**2

    def __call__(self, x: np.ndarray) -> np.ndarray | float:
        """Reward of a raw state `... x D`."""
        y = augment_angles(x, self.angle_dims) - np.asarray(self.target, dtype=float)
        r = np.exp(-0.5 * np.einsum("...i,ij,...j->...", y, self.weight_matrix, y))
        return float(r) if np.ndim(r) == 0 else r
