"""A run's policy as a standalone torch module: u = π(φ(x)) from a raw observation, in plain torch ops.

The module holds ψ as it is (no gradient) and computes what the run's actor computes (:meth:`qtl.build.Parts.actor`):
the angle features φ (θ ↦ sin θ, cos θ), the RBF network (PILCO's, its weights β = (K + σ_π²I)⁻¹ y solved once
here; or MC-PILCO's free weights) or the linear map, the sine squashing to the action bounds, and the centre of
asymmetric bounds (0 for every shipped task). Saved as ``policy.pt`` it is compiled by ``torch.jit.script`` (runs
without qtl: ``torch.jit.load``, or libtorch in C++); as ``policy.pt2`` it is a ``torch.export`` program
(``torch.export.load(path).module()``). Either runs on the CPU in the run's dtype (the input is cast to it). One
action is one learner step: the run held it ``task.action_repeat`` env steps.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Sequence
from pathlib import Path

import torch
from torch import Tensor, nn

from qtl.errors import UserError
from qtl.features import AngleFeatures
from qtl.policies import LinearPolicy, RBFNetwork, RBFPolicy, SquashedPolicy
from qtl.policies.squash import SIN3_FREQ, SIN3_WEIGHT, SIN_WEIGHT

TORCHSCRIPT, EXPORTED_PROGRAM = ".pt", ".pt2"
EXPORT_SUFFIXES = (TORCHSCRIPT, EXPORTED_PROGRAM)


class AngleFeatureMap(nn.Module):
    """y = [x_other, sin θ_a, cos θ_a, …]: :class:`qtl.features.AngleFeatures` as a module."""

    def __init__(self, features: AngleFeatures) -> None:
        super().__init__()
        self.state_dim = features.state_dim
        self.register_buffer("other", torch.tensor(features.other_dims, dtype=torch.long))
        self.register_buffer("angles", torch.tensor(features.angle_dims, dtype=torch.long))

    def forward(self, x: Tensor) -> Tensor:
        """Features `... x (D + K)` of states `... x D`."""
        angles = x.index_select(-1, self.angles)
        trig = torch.stack([angles.sin(), angles.cos()], dim=-1).flatten(-2)
        return torch.cat([x.index_select(-1, self.other), trig], dim=-1)


class SEBasis(nn.Module):
    """Σ_s w_fs exp(−½ ‖(y − c_s)/ℓ_f‖²) per action f: centres `N x D`, weights `F x N`, log ℓ `F x D`."""

    def __init__(self, centres: Tensor, weights: Tensor, log_lengthscales: Tensor) -> None:
        super().__init__()
        inv_lengthscales = _plain(log_lengthscales).neg().exp()  # as qtl.policies.rbf.se_activations forms them
        self.register_buffer("inv_lengthscales", inv_lengthscales)
        self.register_buffer("scaled_centres", _plain(centres)[None, :, :] * inv_lengthscales[:, None, :])
        self.register_buffer("weights", _plain(weights))

    def forward(self, y: Tensor) -> Tensor:
        """Outputs `... x F` for features `... x D` (the squared distance expanded, as the library computes it)."""
        scaled = y.unsqueeze(-2) * self.inv_lengthscales  # ... x F x D
        cross = (scaled.unsqueeze(-2) @ self.scaled_centres.mT).squeeze(-2)  # ... x F x N
        sq_dist = scaled.square().sum(-1).unsqueeze(-1) + self.scaled_centres.square().sum(-1) - 2.0 * cross
        return (torch.exp(-0.5 * sq_dist.clamp_min(0.0)) * self.weights).sum(-1)


class Affine(nn.Module):
    """u = W y + b: weight `F x D`, bias `F`."""

    def __init__(self, weight: Tensor, bias: Tensor) -> None:
        super().__init__()
        self.register_buffer("weight", _plain(weight))
        self.register_buffer("bias", _plain(bias))

    def forward(self, y: Tensor) -> Tensor:
        """Outputs `... x F` for features `... x D`."""
        return y @ self.weight.mT + self.bias


class ExportedPolicy(nn.Module):
    """u = centre + u_max (9 sin z + sin 3z)/8, z = inner(φ(x)): a run's actor on raw observations `... x D`."""

    def __init__(self, features: AngleFeatureMap, inner: nn.Module, bound: Tensor, centre: Tensor) -> None:
        super().__init__()
        self.features = features
        self.inner = inner
        self.sin_weight, self.sin3_weight, self.sin3_freq = SIN_WEIGHT, SIN3_WEIGHT, SIN3_FREQ
        self.register_buffer("bound", _plain(bound))
        self.register_buffer("centre", _plain(centre))

    def forward(self, x: Tensor) -> Tensor:
        """Actions `... x F` (the env's own: centre added) for raw observations `... x D` (cast to the dtype)."""
        z = self.inner(self.features(x.to(self.bound.dtype)))
        return self.centre + self.bound * (self.sin_weight * z.sin() + self.sin3_weight * (self.sin3_freq * z).sin())


def inner_module(policy: nn.Module) -> nn.Module:
    """The unsquashed policy's module: an :class:`SEBasis` (RBF policy or network) or an :class:`Affine` (linear)."""
    with torch.no_grad():
        if isinstance(policy, RBFPolicy):
            return SEBasis(policy.support_points, policy.weights(), policy.log_lengthscales)
        if isinstance(policy, RBFNetwork):
            return SEBasis(policy.centres, policy.weights.mT, policy.log_lengthscales)
        if isinstance(policy, LinearPolicy):
            return Affine(policy.weight, policy.bias)
    raise UserError(f"cannot export a {type(policy).__name__} policy: only the rbf, rbf_network and linear policies")


def exported_policy(
    policy: SquashedPolicy, features: AngleFeatures, centre: Sequence[float] | Tensor | None = None
) -> ExportedPolicy:
    """The squashed ``policy`` on ``features`` as an :class:`ExportedPolicy` (plain torch ops; ``centre`` `F`)."""
    if not isinstance(policy, SquashedPolicy) or policy.batch_shape:
        raise UserError(f"cannot export {type(policy).__name__}: a run's (unbatched) squashed policy is expected")
    bound = _plain(policy.action_bound)
    shift = torch.zeros_like(bound) if centre is None else torch.as_tensor(centre, dtype=bound.dtype).flatten()
    return ExportedPolicy(AngleFeatureMap(features), inner_module(policy.policy), bound, shift).eval()


def check_export_path(path: str | os.PathLike) -> Path:
    """``path`` if a policy can be saved there by its suffix (:data:`EXPORT_SUFFIXES`); else a one-line error."""
    path = Path(path)
    if path.suffix.lower() not in EXPORT_SUFFIXES:
        raise UserError(f"cannot export to {str(path)!r}: the file name must end in {TORCHSCRIPT} (TorchScript, "
                        f"torch.jit.load) or {EXPORTED_PROGRAM} (torch.export.load)")
    return path


def save_policy(path: str | os.PathLike, module: ExportedPolicy) -> Path:
    """Save ``module`` as its suffix says: ``.pt`` scripted (``torch.jit.save``), ``.pt2`` ``torch.export.save``.

    TorchScript takes states `D` or `... x D`; the exported program states `B x D` (B free). torch 2.13 calls
    TorchScript deprecated (its warning is silenced here, ``torch.jit.load`` still says it): ``.pt2`` is its successor.
    """
    path = check_export_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == EXPORTED_PROGRAM:
        example = torch.zeros(2, module.features.state_dim, dtype=module.bound.dtype)
        program = torch.export.export(module, (example,), dynamic_shapes={"x": {0: torch.export.Dim("batch")}})
        torch.export.save(program, str(path))
        return path
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=DeprecationWarning, module=r"torch\.jit")
        torch.jit.save(torch.jit.script(module), str(path))
    return path


def _plain(tensor: Tensor) -> Tensor:
    """A copy of ``tensor`` on the CPU, outside autograd."""
    return tensor.detach().cpu().clone()
