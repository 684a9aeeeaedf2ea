"""``scripts/reference_runs.py``: a rerun's metrics.csv against the recorded one, byte for byte or column by column."""

from __future__ import annotations

from pathlib import Path

from tests.scripts.load import script

reference_runs = script("reference_runs")


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_identical_files_added_columns_and_changed_columns(tmp_path: Path) -> None:
    recorded = write(tmp_path / "a.csv", "episode,return\n0,1.5\n1,2.5\n")
    assert reference_runs.compare(recorded, write(tmp_path / "b.csv", "episode,return\n0,1.5\n1,2.5\n")) == (
        "byte-identical metrics.csv")
    added = write(tmp_path / "c.csv", "episode,return,crossed\n0,1.5,0\n1,2.5,1\n")
    assert reference_runs.compare(recorded, added) == "every recorded column byte-identical; columns added: crossed"
    changed = write(tmp_path / "d.csv", "episode,return,crossed\n0,1.5,0\n1,2.50000001,1\n")
    assert reference_runs.compare(recorded, changed).startswith("DIFFERS metrics.csv (rows 2 vs 2; changed columns "
                                                                "['return']")
    shorter = write(tmp_path / "e.csv", "episode\n0\n1\n")
    assert "missing columns ['return']" in reference_runs.compare(recorded, shorter)
