"""The GP hyper-parameters θ of Eq. 3, per output dimension: the seam every transfer rule uses."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor


def dict_outputs(values: Mapping[str, object]) -> tuple[int, ...]:
    """The state dimensions d a flat θ's ``out{d}/signal_variance`` keys name, in increasing order."""
    found = (key.split("/", 1)[0] for key in values if key.endswith("/signal_variance"))
    return tuple(sorted(int(name[3:]) for name in found if name.startswith("out") and name[3:].isdigit()))


def _column_names(input_dim: int) -> list[str]:
    """``lengthscale/in{i}`` for each of the D inputs, then ``signal_variance``, ``noise_variance``."""
    return [f"lengthscale/in{i}" for i in range(input_dim)] + ["signal_variance", "noise_variance"]


@dataclass(frozen=True)
class GPHyperparameters:
    """θ = (ℓ_1..ℓ_D, α², σ_ε²) for each of the E output dimensions (Eq. 3).

    ``lengthscales``: `E x D` (ℓ, not ℓ²); ``signal_variance``: `E` (α²);
    ``noise_variance``: `E` (σ_ε²). All strictly positive.

    Two flat views exist for the rules of the transfer package, both `E x (D + 2)` with
    columns ``[ℓ_1, …, ℓ_D, α², σ_ε²]``: :meth:`natural` holds the values themselves and
    :meth:`log` their logarithms.
    """

    lengthscales: Tensor
    signal_variance: Tensor
    noise_variance: Tensor

    def __post_init__(self) -> None:
        ls, sv, nv = self.lengthscales, self.signal_variance, self.noise_variance
        if ls.dim() != 2:
            raise ValueError(f"lengthscales must be `E x D`, got shape {tuple(ls.shape)}")
        num_outputs = ls.shape[0]
        for name, value in (("signal_variance", sv), ("noise_variance", nv)):
            if value.shape != (num_outputs,):
                raise ValueError(
                    f"{name} must have shape ({num_outputs},) to match lengthscales "
                    f"{tuple(ls.shape)}, got {tuple(value.shape)}"
                )
        for name, value in (
            ("lengthscales", ls),
            ("signal_variance", sv),
            ("noise_variance", nv),
        ):
            if not torch.isfinite(value).all() or (value <= 0).any():
                raise ValueError(f"{name} must be finite and strictly positive, got {value}")

    @property
    def num_outputs(self) -> int:
        """E, the number of output dimensions (one kernel each)."""
        return self.lengthscales.shape[0]

    @property
    def input_dim(self) -> int:
        """D, the GP input dimension (one length-scale each)."""
        return self.lengthscales.shape[1]

    def natural(self) -> Tensor:
        """θ as `E x (D + 2)`: ``[ℓ_1, …, ℓ_D, α², σ_ε²]`` per output."""
        return torch.cat(
            [self.lengthscales, self.signal_variance[:, None], self.noise_variance[:, None]], dim=-1
        )

    def log(self) -> Tensor:
        """log θ as `E x (D + 2)`: ``[log ℓ_1, …, log ℓ_D, log α², log σ_ε²]`` per output."""
        return self.natural().log()

    @classmethod
    def from_natural(cls, theta: Tensor) -> GPHyperparameters:
        """Build θ from its natural `E x (D + 2)` form."""
        if theta.dim() != 2 or theta.shape[-1] < 3:
            raise ValueError(f"natural θ must be `E x (D + 2)` with D >= 1, got {tuple(theta.shape)}")
        return cls(
            lengthscales=theta[:, :-2].clone(),
            signal_variance=theta[:, -2].clone(),
            noise_variance=theta[:, -1].clone(),
        )

    @classmethod
    def from_log(cls, log_theta: Tensor) -> GPHyperparameters:
        """Build θ from its log `E x (D + 2)` form."""
        return cls.from_natural(log_theta.exp())

    def names(self) -> list[str]:
        """Column names of the flat forms: ``lengthscale/in{i}``, ``signal_variance``, ``noise_variance``."""
        return _column_names(self.input_dim)

    @staticmethod
    def keys(num_outputs: int, input_dim: int, outputs: Sequence[int] | None = None) -> list[str]:
        """The keys of :meth:`as_dict`, ``out{d}/<name>``, output-major in the column order of :meth:`natural`.

        ``outputs``: the state dimension d each output models (default 0..E−1), which names it.
        """
        dims = range(num_outputs) if outputs is None else outputs
        if len(dims) != num_outputs:
            raise ValueError(f"outputs {list(dims)} name {len(dims)} outputs, θ has {num_outputs}")
        return [f"out{d}/{name}" for d in dims for name in _column_names(input_dim)]

    def as_dict(self, outputs: Sequence[int] | None = None) -> dict[str, float]:
        """Flat ``{"out{d}/<name>": value}`` mapping, for logs and CSV files (``outputs``: as :meth:`keys`)."""
        values = self.natural().detach().cpu().reshape(-1)
        keys = self.keys(self.num_outputs, self.input_dim, outputs)
        return {key: float(v) for key, v in zip(keys, values, strict=True)}

    @classmethod
    def from_dict(cls, values: Mapping[str, float | str], prefix: str = "") -> GPHyperparameters:
        """θ in float64 from the keys of :meth:`as_dict` behind ``prefix`` (its inverse); other keys are ignored.

        E.g. ``from_dict(metrics_row, "theta/")`` reads a ``metrics.csv`` row's θ_i columns. The outputs are
        taken in the order of the state dimensions their keys name (:func:`dict_outputs`).
        """
        flat = {key.removeprefix(prefix): value for key, value in values.items() if key.startswith(prefix)}
        outputs = dict_outputs(flat)
        if not outputs or len(flat) % len(outputs):
            raise ValueError(f"not a flat θ behind {prefix!r}: {sorted(flat)}")
        keys = cls.keys(len(outputs), len(flat) // len(outputs) - 2, outputs)
        try:
            natural = torch.tensor([float(flat[key]) for key in keys], dtype=torch.float64)
        except KeyError as err:
            raise ValueError(f"not a flat θ behind {prefix!r}: {err} is missing") from None
        return cls.from_natural(natural.reshape(len(outputs), -1))

    def state_dict(self) -> dict[str, Tensor]:
        """The three tensors by field name, on the CPU (``GPHyperparameters(**state)`` rebuilds θ), for checkpoints."""
        return {"lengthscales": self.lengthscales.cpu(), "signal_variance": self.signal_variance.cpu(),
                "noise_variance": self.noise_variance.cpu()}

    def to(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None) -> GPHyperparameters:
        """The same θ on another dtype/device."""
        return GPHyperparameters(
            lengthscales=self.lengthscales.to(device=device, dtype=dtype),
            signal_variance=self.signal_variance.to(device=device, dtype=dtype),
            noise_variance=self.noise_variance.to(device=device, dtype=dtype),
        )

    def select(self, outputs: Tensor) -> GPHyperparameters:
        """θ of the output dimensions ``outputs`` (indices `k`) alone."""
        return GPHyperparameters(self.lengthscales[outputs], self.signal_variance[outputs],
                                 self.noise_variance[outputs])

    def detach(self) -> GPHyperparameters:
        """The same θ, cut from any autograd graph."""
        return GPHyperparameters(
            self.lengthscales.detach(), self.signal_variance.detach(), self.noise_variance.detach()
        )
