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
