"""A finished source run shared by the transfer tests that only read it."""

from __future__ import annotations

from pathlib import Path

import pytest

from qtl.loop import run
from tests.helpers import tiny_config


@pytest.fixture(scope="session")
def finished_source(tmp_path_factory) -> Path:
    """A finished 0.5 kg source run: one random and two learned episodes (seed 3)."""
    path = tmp_path_factory.mktemp("finished_source")
    run(tiny_config("episodes=2", "seed=3"), path)
    return path


@pytest.fixture(scope="session")
def source_library(tmp_path_factory) -> Path:
    """A directory of two finished cart-pole source runs: ``m0.5`` (0.5 kg pole, k = 0) and ``m3.0`` (3 kg, k = 1)."""
    path = tmp_path_factory.mktemp("library")
    for mass in ("0.5", "3.0"):
        run(tiny_config("episodes=1", "seed=3", f"task.env.pole_mass={mass}"), path / f"m{mass}")
    return path


@pytest.fixture(scope="session")
def mountaincar_source(tmp_path_factory) -> Path:
    """A finished mountain-car run: a source of another task family."""
    path = tmp_path_factory.mktemp("mountaincar")
    run(tiny_config("episodes=1", "seed=3", "task=mountaincar", "task.horizon=6"), path)
    return path
