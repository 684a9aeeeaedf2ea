"""The helicopter's autopilot line: recorded in experiment.yaml when the experiment runs, only read by the report."""

from __future__ import annotations

import json
import logging
import math
import subprocess
import sys

import pytest
import yaml

from qtl.report import ExperimentRecord, autopilot_return, record_reference, write_report
from tests.report.fakes import CARTPOLE, make_experiment, make_helicopter, table_rows

COMMAND = "qtl-train -m +experiment=aircraft seed=0,1,2,3,4"


@pytest.fixture(scope="module")
def mass_6_return() -> float:
    """The autopilot's total reward on the runs' helicopter (task.env of their .hydra/config.yaml: mass 6.0)."""
    return autopilot_return({"mass": 6.0})


def test_autopilot_return_is_a_finite_positive_total_reward():
    total = autopilot_return()
    assert math.isfinite(total) and 0 < total <= 200  # at most 1 per step over the 200-step horizon
    assert autopilot_return({"id": "qtl/Helicopter-v0"}) == total  # an `id` key (as in task.env) is ignored
    assert autopilot_return(seed=0) == total


def test_record_reference_flies_the_runs_helicopter_into_experiment_yaml(tmp_path, mass_6_return):
    root = make_helicopter(tmp_path / "aircraft", {"name": "aircraft", "commands": [COMMAND]})
    reference = record_reference(root)
    assert reference is not None and reference.name == "autopilot"
    assert reference.total == pytest.approx(mass_6_return)
    assert reference.total != pytest.approx(autopilot_return())  # the runs' mass, not the default helicopter
    record = yaml.safe_load((root / "experiment.yaml").read_text())
    assert record == {"name": "aircraft", "commands": [COMMAND],
                      "reference": {"name": "autopilot", "return": reference.total}}


def test_record_reference_leaves_other_experiments_alone(tmp_path):
    root = make_experiment(tmp_path / "cartpole", CARTPOLE)
    assert record_reference(root) is None
    assert not (root / "experiment.yaml").exists()


def test_helicopter_report_has_tables_5_6_and_reads_the_recorded_line(tmp_path, monkeypatch):
    root = make_helicopter(tmp_path / "aircraft", {"name": "aircraft", "commands": [COMMAND],
                                                    "reference": {"name": "autopilot", "return": 123.456}})
    monkeypatch.setattr("qtl.report.autopilot.autopilot_return", lambda *a, **k: pytest.fail("report flew"))
    report = write_report(root, tmp_path / "out")
    assert report == tmp_path / "out" / "report.md"
    text = report.read_text()
    rows = table_rows(text)
    for row in [
        ("PILCO (γ = 0)", "475.00", "1"),  # Table 5
        ("QTL-PILCO Bayesian", "606.50", "1"),
        ("PILCO (γ = 0)", "3 (130.00)", "1"),  # Table 6
        ("QTL-PILCO Bayesian", "2 (132.00)", "1"),
        ("PILCO (γ = 0)", "130.00", "1"),  # Table 1: one seed, just the value
    ]:
        assert row in rows, row
    assert "**Table 5.** Area under the learning curve for the helicopter task." in text
    assert "**Table 4.**" not in text  # no run computed compliance
    assert COMMAND in text and "QTL-PILCO report: aircraft" in text
    tables = json.loads((tmp_path / "out" / "tables.json").read_text())
    assert sorted(tables["tables"]) == ["1", "2", "3", "5", "6"]
    assert tables["experiment"] == "aircraft"
    assert tables["reference"] == {"name": "autopilot", "return": 123.456}  # as recorded, not recomputed
    assert "Dashed: the autopilot's total reward (123.46)." in text
    assert (tmp_path / "out" / "fig_learning_curves.png").stat().st_size > 1000
    assert (tmp_path / "out" / "fig_learning_curves.pdf").stat().st_size > 1000


def test_a_missing_line_is_reported_not_computed(tmp_path, monkeypatch, caplog):
    root = make_helicopter(tmp_path / "aircraft", {"name": "aircraft", "commands": [COMMAND]})
    monkeypatch.setattr("qtl.report.autopilot.autopilot_return", lambda *a, **k: pytest.fail("report flew"))
    with caplog.at_level(logging.WARNING, logger="qtl.report"):
        report = write_report(root)
    assert "records no autopilot reference" in caplog.text and "--record-reference" in caplog.text
    assert json.loads((report.parent / "tables.json").read_text())["reference"] is None
    assert "Dashed" not in report.read_text()
    assert ExperimentRecord.read(root).reference is None  # the report writes nothing back


def test_cli_records_the_line_when_asked(tmp_path, mass_6_return):
    root = make_helicopter(tmp_path / "aircraft")  # no experiment.yaml: the helicopter label decides
    done = subprocess.run([sys.executable, "-m", "qtl.report.cli", str(root), "--record-reference"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    line = json.loads((root / "report" / "tables.json").read_text())["reference"]
    assert line == {"name": "autopilot", "return": pytest.approx(mass_6_return)}
    assert ExperimentRecord.read(root).reference.total == pytest.approx(mass_6_return)
