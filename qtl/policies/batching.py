"""Restarts as a leading batch dimension of ψ: R policies evaluated by one batched rollout.

A policy whose ψ tensors are stacked `R x ...` (``batch_shape`` `R`) is R policies at once: its
moment map and ``forward`` broadcast over R, so one propagation through it predicts R returns
`R`, and the gradient of their sum is block-separable (restart r's ψ gets ∂V_r/∂ψ_r only).
:func:`batched_policy` makes such a copy; :func:`set_psi` swaps stacked ψ into a policy in place
(what the batched policy search does, so that a propagator built on the plain policy serves it);
:func:`restart_state` reads restart r back as a plain state dict.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping, Sequence

import torch
from torch import Tensor, nn

from qtl.policies.base import Policy


def psi_names(policy: nn.Module) -> list[str]:
    """Names of ψ, the parameters of ``policy``, in ``named_parameters`` order."""
    return [name for name, _ in policy.named_parameters()]


def stack_psi(states: Sequence[Mapping[str, Tensor]], names: Sequence[str]) -> dict[str, Tensor]:
    """ψ of R state dicts stacked along a new leading restart dimension: `R x ...` per name."""
    if not states:
        raise ValueError("stack_psi needs at least one state")
    return {name: torch.stack([state[name].detach() for state in states]) for name in names}


def set_psi(policy: Policy, psi: Mapping[str, Tensor], batch_shape: Sequence[int] = ()) -> dict[str, nn.Parameter]:
    """Make ``psi`` (`*batch_shape x ...` per name, every ψ name) the parameters of ``policy``, in place.

    Tensors that are not already parameters are wrapped as parameters that require gradients where
    the parameters they replace do (a fixed part of ψ stays fixed).
    Every policy inside ``policy`` (a squashed policy's inner one too) gets ``batch_shape``.
    Returns the parameters it replaced, by name, so that a caller can put them back.
    """
    names = psi_names(policy)
    if set(psi) != set(names):
        raise ValueError(f"set_psi needs exactly the ψ names {names}, got {sorted(psi)}")
    shape, old_batch = torch.Size(batch_shape), len(policy.batch_shape)
    replaced = {}
    for name in names:
        owner_name, _, attr = name.rpartition(".")
        owner = policy.get_submodule(owner_name)
        value, old = psi[name], getattr(owner, attr)
        if value.shape != shape + old.shape[old_batch:]:
            raise ValueError(f"{name} must be `{tuple(shape + old.shape[old_batch:])}`, got {tuple(value.shape)}")
        replaced[name] = old
        setattr(owner, attr, value if isinstance(value, nn.Parameter)
                else nn.Parameter(value, requires_grad=old.requires_grad))
    for module in policy.modules():
        if isinstance(module, Policy):
            module.batch_shape = shape
    return replaced


def batched_policy(policy: Policy, restarts: int) -> Policy:
    """A copy of ``policy`` whose ψ are ``restarts`` stacked copies of its ψ: `R x ...` each, ``batch_shape`` `R`."""
    if restarts < 1:
        raise ValueError(f"restarts must be >= 1, got {restarts}")
    if policy.batch_shape:
        raise ValueError(f"the policy is batched already (batch_shape {tuple(policy.batch_shape)})")
    copied = copy.deepcopy(policy)
    psi = {
        name: nn.Parameter(p.detach().expand(restarts, *p.shape).clone(), requires_grad=p.requires_grad)
        for name, p in copied.named_parameters()
    }
    set_psi(copied, psi, (restarts,))
    return copied


def restart_state(policy: Policy, restart: int) -> dict[str, Tensor]:
    """Restart ``restart``'s state dict of a batched policy (ψ sliced, buffers as they are), for the plain policy."""
    if len(policy.batch_shape) != 1:
        raise ValueError(f"restart_state needs one restart dimension, the policy has {tuple(policy.batch_shape)}")
    psi = set(psi_names(policy))
    return {name: value[restart].detach().clone() if name in psi else value.detach().clone()
            for name, value in policy.state_dict().items()}
