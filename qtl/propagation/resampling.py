"""Gaussian resampling of particles (PIPPS's "GR", Parmas et al. 2018): fresh draws from their fitted Gaussian."""

from __future__ import annotations

from torch import Tensor

from qtl.gaussian import matrix_root, sample_moments


def gaussian_resample(x: Tensor, noise: Tensor) -> Tensor:
    """P draws m̂ + L̂ ε' from the Gaussian fitted to particles ``x`` `... x P x D`; ``noise`` ε' `P x D`."""
    fitted = sample_moments(x)  # mean `... x D`, cov `... x D x D`
    return fitted.mean[..., None, :] + noise @ matrix_root(fitted.cov).mT
