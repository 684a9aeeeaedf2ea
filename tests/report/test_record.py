"""``experiment.yaml``: name, commands and the reference line, written and read back."""

from __future__ import annotations

import pytest
import yaml

from qtl.report import EXPERIMENT_FILE, ExperimentRecord, Reference


def test_record_round_trip_and_an_absent_file_is_empty(tmp_path):
    assert ExperimentRecord.read(tmp_path) == ExperimentRecord()
    record = ExperimentRecord("aircraft", ["qtl-train experiment=aircraft_source", "qtl-train experiment=aircraft"])
    record.write(tmp_path)
    assert yaml.safe_load((tmp_path / EXPERIMENT_FILE).read_text()) == {"name": "aircraft",
                                                                          "commands": record.commands}
    assert ExperimentRecord.read(tmp_path) == record
    with_line = record.with_reference(Reference("autopilot", 151.25))
    with_line.write(tmp_path)
    assert yaml.safe_load((tmp_path / EXPERIMENT_FILE).read_text())["reference"] == {"name": "autopilot",
                                                                                      "return": 151.25}
    assert ExperimentRecord.read(tmp_path) == with_line


@pytest.mark.parametrize(("text", "message"), [
    ("- a list\n", "expected a mapping with 'name' and 'commands', got list"),
    ("name: x\nreference: 12.0\n", "'reference' must be a mapping with 'name' and 'return'"),
    ("name: x\nreference: {name: autopilot}\n", "'reference' must be a mapping with 'name' and 'return'"),
])
def test_a_malformed_record_is_named(tmp_path, text, message):
    (tmp_path / EXPERIMENT_FILE).write_text(text)
    with pytest.raises(ValueError, match=message):
        ExperimentRecord.read(tmp_path)
