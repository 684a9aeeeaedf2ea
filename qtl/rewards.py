"""The saturating reward of Eq. 13 in torch: per state, and its expectation under a Gaussian state.

`r(x) = exp(−½ (y − y*)ᵀ W (y − y*))`, y the angle-augmented state (``qtl.features``), built
from the same declarative spec the environments use (``qtl.envs.rewards.SaturatingReward``:
``state_dim``, ``angle_dims``, ``target`` y*, ``weight_matrix`` W with the width folded in).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Protocol

import torch
from numpy.typing import ArrayLike
from torch import Tensor

from qtl.features import AngleFeatures
from qtl.gaussian import Gaussian, cholesky, nan_where
from qtl.kernels.engine import DEFAULT_ENGINE, Engine

# Eigenvalues of W below this fraction of the largest are treated as zero (W is PSD).
WEIGHT_RANK_TOL = 1e-12


class RewardSpec(Protocol):
    """A declarative saturating reward (as ``qtl.envs.rewards.SaturatingReward``): what :meth:`from_spec` reads."""

    @property
    def state_dim(self) -> int:
        """D, the raw state dimension."""
        ...

    @property
    def angle_dims(self) -> Sequence[int]:
        """The angle dimensions of the raw state."""
        ...

    @property
    def target(self) -> Sequence[float]:
        """y* `D + K`, in augmented coordinates."""
        ...

    @property
    def weight_matrix(self) -> ArrayLike:
        """W `(D + K) x (D + K)` with the width folded in."""
        ...


class ExpectedSaturatingReward:
    """`r(x) = exp(−½ (y − y*)ᵀ W (y − y*))` (Eq. 13) with y = [x_other, sin θ_a, cos θ_a, …].

    ``target`` `D + K` and ``weight_matrix`` `(D + K) x (D + K)` (symmetric PSD) live in the
    augmented coordinates of :class:`qtl.features.AngleFeatures` with ``angle_dims``.
    """

    def __init__(
        self,
        state_dim: int,
        angle_dims: Sequence[int],
        target: Sequence[float] | Tensor,
        weight_matrix: ArrayLike | Tensor,
    ) -> None:
        self.features = AngleFeatures(state_dim, angle_dims)
        aug = self.features.output_dim
        target = torch.as_tensor(target, dtype=torch.float64)
        weight = torch.as_tensor(weight_matrix, dtype=torch.float64)
        if target.shape != (aug,) or weight.shape != (aug, aug):
            raise ValueError(
                f"target must be `{aug}` and weight_matrix `{aug} x {aug}`, got "
                f"{tuple(target.shape)} and {tuple(weight.shape)}"
            )
        if not torch.allclose(weight, weight.mT):
            raise ValueError("weight_matrix must be symmetric")
        eigval, eigvec = torch.linalg.eigh(weight)
        if eigval.min() < -WEIGHT_RANK_TOL * max(eigval.abs().max().item(), 1.0):
            raise ValueError("weight_matrix must be positive semi-definite")
        keep = eigval > WEIGHT_RANK_TOL * eigval.max()
        self.target = target
        self.weight = weight
        # W = Cᵀ C with C `r x (D + K)`, r = rank W: the expectation works in the r-D range of W.
        self.factor = eigval[keep].sqrt()[:, None] * eigvec[:, keep].mT

    @classmethod
    def from_spec(cls, spec: RewardSpec) -> ExpectedSaturatingReward:
        """Build from any object with ``state_dim``, ``angle_dims``, ``target``, ``weight_matrix``."""
        return cls(spec.state_dim, spec.angle_dims, spec.target, spec.weight_matrix)

    def widened(self, scale: float) -> ExpectedSaturatingReward:
        """The same reward with its width × ``scale`` (W / scale²): a wider search reward (MC-PILCO's cost)."""
        if not scale > 0:
            raise ValueError(f"reward width scale must be > 0, got {scale}")
        return ExpectedSaturatingReward(self.state_dim, self.features.angle_dims, self.target, self.weight / scale**2)

    @property
    def state_dim(self) -> int:
        """D, the raw state dimension."""
        return self.features.state_dim

    def __call__(self, x: Tensor) -> Tensor:
        """Reward of raw states `... x D` (e.g. particles): `...` (Eq. 13)."""
        diff = (self.features(x) - self.target.to(x)) @ self.factor.to(x).mT
        return torch.exp(-0.5 * diff.square().sum(-1))

    def expected_augmented(self, y: Gaussian) -> Tensor:
        """E[r] for Gaussian augmented features y ~ N(m, S): `...` (Eq. 13 in expectation).

        E[exp(−½ dᵀWd)] = |I + C S Cᵀ|^{-1/2} exp(−½ eᵀ (I + C S Cᵀ)⁻¹ e), e = C (m − y*).
        """
        factor = self.factor.to(y.mean)
        proj_cov = factor @ y.cov @ factor.mT
        eye = torch.eye(factor.shape[0], dtype=proj_cov.dtype, device=proj_cov.device)
        chol, failed = cholesky(proj_cov + eye)  # not positive-definite: raises, or NaN (qtl.gaussian)
        err = (y.mean - self.target.to(y.mean)) @ factor.mT
        white = torch.linalg.solve_triangular(chol, err[..., None], upper=False).squeeze(-1)
        half_logdet = torch.diagonal(chol, dim1=-2, dim2=-1).log().sum(-1)
        return nan_where(failed, torch.exp(-half_logdet - 0.5 * white.square().sum(-1)))

    def expected(self, state: Gaussian, engine: Engine = DEFAULT_ENGINE) -> Tensor:
        """E[r(x)] for a raw Gaussian state `... x D` → `...` (Eq. 13).

        Exact when there are no angle dimensions; otherwise, as PILCO, the exact expectation
        under the moment-matched Gaussian of the augmented state y (its moments by ``engine``).
        """
        return self.expected_augmented(self.features.moments(state, engine).output)


class RewardMixture:
    """r(x) = Σ_k w_k r_k(x), a weighted sum of saturating rewards (Eq. 13 each): a search reward wide and sharp.

    Its expectations are the same weighted sums of the parts' (exact: the expectation is linear).
    """

    def __init__(self, parts: Sequence[ExpectedSaturatingReward], weights: Sequence[float]) -> None:
        if len(parts) != len(weights) or not parts:
            raise ValueError(
                f"a reward mixture needs as many weights as parts (>= 1), got {len(parts)} and {len(weights)}"
            )
        if any(not w >= 0 for w in weights) or sum(weights) <= 0:
            raise ValueError(f"mixture weights must be >= 0 with a positive sum, got {list(weights)}")
        if len({part.state_dim for part in parts}) != 1:
            raise ValueError("the parts of a reward mixture must share the state dimension")
        self.parts = list(parts)
        self.weights = [float(w) for w in weights]

    @property
    def state_dim(self) -> int:
        """D, the raw state dimension."""
        return self.parts[0].state_dim

    def __call__(self, x: Tensor) -> Tensor:
        """Reward of raw states `... x D`: `...`."""
        return sum(w * part(x) for w, part in zip(self.weights, self.parts, strict=True))

    def expected(self, state: Gaussian, engine: Engine = DEFAULT_ENGINE) -> Tensor:
        """E[r(x)] for a raw Gaussian state `... x D` → `...`: the weighted sum of the parts' (Eq. 13)."""
        return sum(w * part.expected(state, engine) for w, part in zip(self.weights, self.parts, strict=True))


class AngleDistanceReward:
    """r(x) = exp(−½ Σ_d (δ_d / σ_d)²): δ_d the wrapped angle to the target on angle dims, else x_d − x*_d.

    A search cost on the raw state, as MC-PILCO's cart-pole cost exp(−((|θ| − π)/ℓ_θ)² − (x/ℓ_x)²)
    (σ = ℓ/√2): unlike a saturating reward of (sin θ, cos θ) (Eq. 13), it grows linearly with the
    swing away from hanging (|θ| has a kink there), so a swing-up search gets a first-order signal.
    ``target`` and ``widths`` `D`; a width of inf leaves its dimension out. Per state only: it has no
    Gaussian expectation (particle searches score drawn states). ``absolute_angles``: δ = |θ| − θ* on the
    raw (unwrapped) angle instead, MC-PILCO's form as written, which scores each turn beyond the first as
    far from the target (a wrapped δ makes a full turn-over free).
    """

    def __init__(
        self, state_dim: int, angle_dims: Sequence[int], target: Sequence[float], widths: Sequence[float],
        *, absolute_angles: bool = False,
    ) -> None:
        target_t = torch.as_tensor(target, dtype=torch.float64)
        widths_t = torch.as_tensor(widths, dtype=torch.float64)
        if target_t.shape != (state_dim,) or widths_t.shape != (state_dim,):
            raise ValueError(f"target and widths must be `{state_dim}`, got {tuple(target_t.shape)} and "
                             f"{tuple(widths_t.shape)}")
        if not bool((widths_t > 0).all()) or bool(torch.isinf(widths_t).all()):
            raise ValueError(f"widths must be > 0 (inf: dimension left out), at least one finite, got {list(widths)}")
        used = torch.isfinite(widths_t)
        if not bool(torch.isfinite(target_t[used]).all()):
            raise ValueError(f"the target must be finite on every dimension with a finite width, got {list(target)}")
        if any(not 0 <= a < state_dim for a in angle_dims):
            raise ValueError(f"angle_dims {list(angle_dims)} must be below {state_dim}")
        self._state_dim = state_dim
        self.angle_dims = tuple(int(a) for a in angle_dims)
        self.dims = torch.nonzero(used).flatten()  # the dimensions it sees
        self.target = target_t[self.dims]
        self.inv_widths = widths_t[self.dims].reciprocal()
        self.is_angle = torch.tensor([int(d) in self.angle_dims for d in self.dims])
        self.absolute_angles = bool(absolute_angles)

    @property
    def state_dim(self) -> int:
        """D, the raw state dimension."""
        return self._state_dim

    def __call__(self, x: Tensor) -> Tensor:
        """Reward of raw states `... x D`: `...`."""
        raw, target = x[..., self.dims], self.target.to(x)
        diff = raw - target
        if self.absolute_angles:
            angular = raw.abs() - target  # every turn beyond the first counts
        else:
            angular = torch.remainder(diff + math.pi, 2 * math.pi) - math.pi  # in [−π, π)
        diff = torch.where(self.is_angle.to(x.device), angular, diff)
        return torch.exp(-0.5 * (diff * self.inv_widths.to(x)).square().sum(-1))

    def expected(self, state: Gaussian, engine: Engine = DEFAULT_ENGINE) -> Tensor:
        """No Gaussian expectation: a UserError-worthy misuse, raised as ValueError."""
        raise ValueError("an angle-distance search cost has no Gaussian expectation: use propagation.expected_reward="
                         "false (score the drawn states)")
