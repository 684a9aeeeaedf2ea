"""The paper's numbers beside the report's: ``here · paper`` cells of hand-computed experiments, NC seeds marked."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from qtl.report import write_report
from qtl.report.paper import NC, PAPER, PAPER_COMPLIANCE, UNKNOWN, paper_text
from tests.report.fakes import CARTPOLE, make_experiment, make_helicopter, table_rows


def _named(root: Path, name: str) -> Path:
    """``root`` with an ``experiment.yaml`` naming it ``name``."""
    (root / "experiment.yaml").write_text(yaml.safe_dump({"name": name, "commands": []}))
    return root


def _report(root: Path) -> tuple[str, dict]:
    """(report.md text, tables.json) of ``root``."""
    report = write_report(root)
    return report.read_text(), json.loads((report.parent / "tables.json").read_text())


def _section(text: str) -> str:
    """The report's "Beside the paper" section."""
    start = text.index("## Beside the paper")
    return text[start:text.index("\n## ", start + 1)]


def test_paper_text_prints_numbers_and_the_papers_words():
    assert paper_text(36.95, 2) == "36.95"
    assert paper_text(25, 1, whole=True) == "25"
    assert paper_text(NC, 2) == "NC" and paper_text(UNKNOWN, 1, whole=True) == "unknown"
    assert paper_text(None, 2) == "—"


def test_paper_tables_1_to_3_have_every_approach_and_mass():
    for metric, table in PAPER["cartpole"].items():
        assert len(table) == 7, metric
        assert all(list(row) == ["m0.8", "m1.0", "m1.5", "m2.0"] for row in table.values()), metric
    assert PAPER["cartpole"]["final_performance"]["qtl_gamma_1"]["m2.0"] == NC
    assert PAPER["cartpole"]["time_to_convergence"]["policy_transfer"]["m1.5"] == UNKNOWN
    assert PAPER["cartpole"]["auc"]["qtl_bayesian"]["m2.0"] == 539.79


def test_cartpole_cells_sit_beside_tables_1_to_3_with_nc_seeds_marked(tmp_path):
    text, tables = _report(_named(make_experiment(tmp_path / "cartpole", CARTPOLE), "cartpole"))
    rows = table_rows(_section(text))
    for row in [
        # Table 1: PILCO's m2.0 seeds end at 20 and 14 (success is >= 30), Bayesian's seed 0 at 20.
        ("PILCO (γ = 0)", "33.00 ± 4.24 · 33.32", "17.00 ± 4.24 (NC 2/2) · 29.71", "2"),
        ("QTL-PILCO Bayesian", "40.00 ± 0.00 · 32.68", "25.00 ± 7.07 (NC 1/2) · 29.97", "2"),
        ("PILCO (γ = 0)", "125.50 ± 28.99 · 218.63", "57.00 ± 4.24 · 204.41", "2"),  # Table 2
        ("QTL-PILCO Bayesian", "185.00 ± 7.07 · 602.55", "107.50 ± 17.68 · 539.79", "2"),
        ("PILCO (γ = 0)", "2.0 ± 1.4 · 22", "3.5 ± 0.7 · 25", "2"),  # Table 3
        ("QTL-PILCO Bayesian", "1.5 ± 0.7 · 10", "1.5 ± 0.7 · 12", "2"),
    ]:
        assert row in rows, row
    positions = [text.index(f"**Table {n} beside the paper.**") for n in (1, 2, 3)]
    assert positions == sorted(positions)
    assert text.index("**Table 3.**") < positions[0] < text.index("**Table S1.**")
    assert tables["paper"]["tables"] == {"final_performance": 1, "auc": 2, "time_to_convergence": 3}
    assert tables["paper"]["final_performance"]["policy_transfer"]["m1.5"] == NC
    assert tables["paper"]["compliance"] == {}


def test_cells_the_paper_lacks_get_a_dash(tmp_path):
    runs = {"my_rule": {"m1.5": CARTPOLE["pilco"]["m1.5"]}, "pilco": {"m3.0": CARTPOLE["pilco"]["m1.5"]}}
    text, _ = _report(_named(make_experiment(tmp_path / "cartpole", runs), "cartpole"))
    rows = table_rows(_section(text))
    assert ("my_rule", "33.00 ± 4.24 · —", "—", "2") in rows  # an approach the paper has not
    assert ("PILCO (γ = 0)", "—", "33.00 ± 4.24 · —", "2") in rows  # a mass the paper has not


def test_helicopter_sits_beside_tables_5_and_6(tmp_path):
    text, tables = _report(make_helicopter(tmp_path / "aircraft", {"name": "aircraft", "commands": []}))
    rows = table_rows(_section(text))
    assert ("PILCO (γ = 0)", "130.00 · 132.50", "1") in rows  # Table 6's final performance
    assert ("QTL-PILCO Bayesian", "606.50 · 3803.70", "1") in rows  # Table 5
    assert ("QTL-PILCO Bayesian", "2 · 19", "1") in rows  # Table 6's time to convergence
    assert "**Table 5 beside the paper.**" in text and "**Table 6 beside the paper.**" in text
    assert tables["paper"]["auc"]["pilco"]["helicopter"] == 2225.4


def test_mountaincar_compliance_sits_beside_table_4(tmp_path):
    runs = {approach: {{"m1.5": "p0.5", "m2.0": "p3.0"}[label]: seeds for label, seeds in by_label.items()}
            for approach, by_label in CARTPOLE.items()}
    text, tables = _report(_named(make_experiment(tmp_path / "mountaincar", runs), "mountaincar"))
    section = _section(text)
    rows = table_rows(section)
    assert ("p0.5", "0.70 ± 0.14", "0.64", "2") in rows  # Bayesian runs' last compliance
    assert ("p3.0", "0.25", "0.34", "1") in rows  # PILCO's, the one seed with compliance there
    assert "Table 1 beside" not in section and "Each cell" not in section  # Fig. 2 is curves only
    assert tables["paper"]["compliance"] == PAPER_COMPLIANCE["mountaincar"]


@pytest.mark.parametrize("name", [None, "cartpole_quick"])
def test_an_experiment_the_paper_did_not_run_has_no_paper_section(tmp_path, name):
    root = make_experiment(tmp_path / "exp", CARTPOLE)
    if name is not None:
        _named(root, name)
    text, tables = _report(root)
    assert "## Beside the paper" not in text
    assert tables["paper"] is None
