"""The cart-pole experiment's report, written once for the report tests."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from qtl.report import write_report
from tests.report.fakes import CARTPOLE, make_experiment


@pytest.fixture(scope="package")
def cartpole(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str, dict]:
    """(report path, report.md text, tables.json) of :data:`~tests.report.fakes.CARTPOLE`."""
    root = make_experiment(tmp_path_factory.mktemp("cartpole"), CARTPOLE)
    report = write_report(root)
    return report, report.read_text(), json.loads((report.parent / "tables.json").read_text())
