"""Persistence of the GP dynamics model: its data and θ as a state dict, on disk."""

from __future__ import annotations

import os
from typing import Self

import torch

from qtl.models.hyperparameters import GPHyperparameters

CHECKPOINT_FORMAT = "qtl.DynamicsGP"
CHECKPOINT_VERSION = 1


class GPCheckpoint:
    """Saving and loading of :class:`~qtl.models.DynamicsGP` (a mixin): ``state``/``from_state``, ``save``/``load``."""

    def state(self) -> dict:
        """Everything needed to rebuild this model (data and θ), as tensors and primitives."""
        theta = self.hyperparameters
        state = {
            "format": CHECKPOINT_FORMAT,
            "version": CHECKPOINT_VERSION,
            "train_x": self.train_x.detach().cpu(),
            "train_y": self.train_y.detach().cpu(),
            "lengthscales": theta.lengthscales.cpu(),
            "signal_variance": theta.signal_variance.cpu(),
            "noise_variance": theta.noise_variance.cpu(),
            "outputs": list(self.outputs),
            "state_dim": self.state_dim,
            "constant_outputs": list(self.constant_outputs),
            "constant_delta": self.constant_delta.detach().cpu(),
        }
        if self.extra_noise is not None:  # per-point extra noise c `n x E` (source samples)
            state["extra_noise"] = self.extra_noise.detach().T.cpu()
        return state

    @classmethod
    def from_state(
        cls, state: dict, *, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu"
    ) -> Self:
        """Rebuild a model from :meth:`state` on ``device``; a malformed state raises ValueError.

        A state without ``outputs`` (written before models held them) models all outputs, 0..E−1, of an E-D state.
        """
        if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
            raise ValueError("not a DynamicsGP state (missing or wrong 'format' entry)")
        if state.get("version") != CHECKPOINT_VERSION:
            raise ValueError(f"unsupported DynamicsGP state version {state.get('version')!r}")
        missing = {"train_x", "train_y", "lengthscales", "signal_variance", "noise_variance"}
        missing -= state.keys()
        if missing:
            raise ValueError(f"DynamicsGP state lacks {sorted(missing)}")
        theta = GPHyperparameters(
            state["lengthscales"].to(dtype),
            state["signal_variance"].to(dtype),
            state["noise_variance"].to(dtype),
        )
        return cls(state["train_x"].to(device), state["train_y"].to(device), theta, outputs=state.get("outputs"),
                   state_dim=state.get("state_dim"), constant_outputs=state.get("constant_outputs", ()),
                   constant_delta=state.get("constant_delta"), extra_noise=state.get("extra_noise"), dtype=dtype)

    def save(self, path: str | os.PathLike) -> None:
        """Write data and θ to ``path`` (an ExactGP's state_dict alone lacks the data)."""
        torch.save(self.state(), path)

    @classmethod
    def load(
        cls, path: str | os.PathLike, *, dtype: torch.dtype = torch.float64, device: torch.device | str = "cpu"
    ) -> Self:
        """Read a model written by :meth:`save` onto ``device``; a missing or corrupt file raises a clear error."""
        if not os.path.isfile(path):
            raise FileNotFoundError(f"no DynamicsGP checkpoint at {os.fspath(path)!r}")
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as err:  # torch raises many types for a damaged file
            raise ValueError(f"corrupt DynamicsGP checkpoint {os.fspath(path)!r}: {err}") from err
        try:
            return cls.from_state(state, dtype=dtype, device=device)
        except ValueError as err:
            raise ValueError(f"corrupt DynamicsGP checkpoint {os.fspath(path)!r}: {err}") from err
