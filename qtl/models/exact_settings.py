"""The GPyTorch settings under which an exact GP's solves and log-determinants are exact Cholesky factorisations."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import gpytorch

# Dataset size below which GPyTorch uses Cholesky; far above any exact-GP dataset we handle.
EXACT_CHOLESKY_SIZE = 10**7


@contextlib.contextmanager
def exact_gp_settings() -> Iterator[None]:
    """GPyTorch settings under which every solve and log-determinant is an exact Cholesky.

    GPyTorch switches to conjugate gradients and Lanczos above 800 points by default; moment
    matching and evidence maximisation in qtl need exact solves at every dataset size.
    """
    with (
        gpytorch.settings.max_cholesky_size(EXACT_CHOLESKY_SIZE),
        gpytorch.settings.fast_computations(
            covar_root_decomposition=False, log_prob=False, solves=False
        ),
        gpytorch.settings.fast_pred_var(False),
    ):
        yield
