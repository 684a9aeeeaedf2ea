"""``write_report``: tables.json holds the hand-computed numbers, report.md their table cells; the CLI."""

from __future__ import annotations

import math
import shutil
import subprocess
import sys

import pytest

from qtl.report import write_report
from tests.report.fakes import CARTPOLE, NAN, make_experiment, table_rows, write_run


def test_tables_json_holds_the_hand_computed_numbers(cartpole):
    report, _, tables = cartpole
    assert report == report.parent.parent / "report" / "report.md"  # default out dir: <root>/report
    assert tables["approaches"] == {"pilco": "PILCO (γ = 0)", "qtl_bayesian": "QTL-PILCO Bayesian"}
    assert tables["labels"] == ["m1.5", "m2.0"]
    assert tables["sources"] == {"0": 4, "1": 4}
    expected = {  # metric -> approach -> label -> (mean, std, per seed)
        "final_performance": {
            "pilco": {"m1.5": (33.0, math.sqrt(18), [30, 36]), "m2.0": (17.0, math.sqrt(18), [20, 14])},
            "qtl_bayesian": {"m1.5": (40.0, 0.0, [40, 40]), "m2.0": (25.0, math.sqrt(50), [20, 30])},
        },
        "auc": {
            "pilco": {"m1.5": (125.5, 41 / math.sqrt(2), [105, 146]), "m2.0": (57.0, math.sqrt(18), [60, 54])},
            "qtl_bayesian": {"m1.5": (185.0, math.sqrt(50), [180, 190]), "m2.0": (107.5, 25 / math.sqrt(2), [95, 120])},
        },
        "time_to_convergence": {
            "pilco": {"m1.5": (2.0, math.sqrt(2), [3, 1]), "m2.0": (3.5, math.sqrt(0.5), [3, 4])},
            "qtl_bayesian": {"m1.5": (1.5, math.sqrt(0.5), [2, 1]), "m2.0": (1.5, math.sqrt(0.5), [1, 2])},
        },
    }
    for metric, by_approach in expected.items():
        for approach, by_label in by_approach.items():
            for label, (mean, std, per_seed) in by_label.items():
                got = tables[metric][approach][label]
                where = f"{metric} {approach} {label}"
                assert got["mean"] == pytest.approx(mean), where
                assert got["std"] == pytest.approx(std), where
                assert got["n"] == 2, where
                assert got["per_seed"] == {"0": pytest.approx(per_seed[0]), "1": pytest.approx(per_seed[1])}, where
    # Table 4: Bayesian runs where they have compliance; on m2.0 PILCO's, only the seed whose last
    # (common) episode has one.
    assert tables["compliance"]["m1.5"] == {"approach": "qtl_bayesian", "mean": pytest.approx(0.7),
                                            "std": pytest.approx(math.sqrt(0.02)), "n": 2,
                                            "per_seed": {"0": 0.6, "1": 0.8}}
    assert tables["compliance"]["m2.0"] == {"approach": "pilco", "mean": 0.25, "std": None, "n": 1,
                                            "per_seed": {"0": 0.25}}
    assert tables["cells"]["pilco"]["m2.0"] == {"seeds": [0, 1], "episodes": 6, "truncated": True,
                                                "run_episodes": {"0": 6, "1": 8}}
    assert tables["cells"]["qtl_bayesian"]["m1.5"]["truncated"] is False
    assert sorted(tables["tables"]) == ["1", "2", "3", "4"]
    assert tables["reference"] is None  # no autopilot line for the cart-pole


def test_report_markdown_has_the_table_cells(cartpole):
    _, text, _ = cartpole
    rows = table_rows(text)
    for row in [
        ("Approach", "m1.5", "m2.0", "Seeds"),
        ("PILCO (γ = 0)", "33.00 ± 4.24", "17.00 ± 4.24", "2"),  # Table 1
        ("QTL-PILCO Bayesian", "40.00 ± 0.00", "25.00 ± 7.07", "2"),
        ("PILCO (γ = 0)", "125.50 ± 28.99", "57.00 ± 4.24", "2"),  # Table 2
        ("QTL-PILCO Bayesian", "185.00 ± 7.07", "107.50 ± 17.68", "2"),
        ("PILCO (γ = 0)", "2.0 ± 1.4", "3.5 ± 0.7", "2"),  # Table 3
        ("QTL-PILCO Bayesian", "1.5 ± 0.7", "1.5 ± 0.7", "2"),
        ("m1.5", "QTL-PILCO Bayesian", "0.70 ± 0.14", "2"),  # Table 4
        ("m2.0", "PILCO (γ = 0)", "0.25", "1"),
    ]:
        assert row in rows, row
    positions = [text.index(f"**Table {n}.**") for n in (1, 2, 3, 4)]
    assert positions == sorted(positions)
    assert "**Table 5.**" not in text and "**Table 6.**" not in text  # two labels
    assert rows.index(("PILCO (γ = 0)", "33.00 ± 4.24", "17.00 ± 4.24", "2")) < rows.index(
        ("QTL-PILCO Bayesian", "40.00 ± 0.00", "25.00 ± 7.07", "2"))
    # What was found, with the common-prefix rule stated for the one cell it cut.
    assert "seed_0: 6, seed_1: 8" in text and "the common first 6 episodes are used" in text
    assert text.count("the common first") == 1
    # No experiment.yaml: the overrides of one run per cell (and of a source run).
    assert "`qtl-train seed=0 approach=qtl_bayesian task.env.pole_mass=2.0`" in text
    assert "`qtl-train seed=0 approach=pilco task.env.pole_mass=1.5`" in text
    assert "`source/seed_0`: `qtl-train seed=0`" in text
    assert "![learning curves](fig_learning_curves.png)" in text


def test_cli_prints_the_report_path(tmp_path):
    root = make_experiment(tmp_path / "exp", {"pilco": {"m1.5": CARTPOLE["pilco"]["m1.5"]}}, sources=0)
    done = subprocess.run([sys.executable, "-m", "qtl.report.cli", str(root), "--out", str(tmp_path / "out")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(tmp_path / "out" / "report.md")
    assert ("PILCO (γ = 0)", "33.00 ± 4.24", "2") in table_rows((tmp_path / "out" / "report.md").read_text())


def test_cli_refuses_an_unreadable_final_policies_file_in_one_line_writing_nothing(tmp_path):
    root = make_experiment(tmp_path / "exp", {"pilco": {"m1.5": CARTPOLE["pilco"]["m1.5"]}}, sources=0)
    (root / "final_policies.json").write_text("{}")
    done = subprocess.run([sys.executable, "-m", "qtl.report.cli", str(root)], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 1 and done.stdout == "" and done.stderr.startswith("qtl-report: ")
    assert done.stderr.count("\n") == 1 and "is not what qtl-evaluate writes" in done.stderr
    assert not (root / "report").exists()


def test_the_report_names_the_source_each_run_of_several_sources_chose(tmp_path):
    runs = {"qtl_bayesian": {"m0.6": {0: ([10, 20, 30], [NAN, 0.9, 0.9]), 1: ([10, 20, 30], [NAN, 0.8, 0.8])}}}
    root = make_experiment(tmp_path / "exp", runs)
    several = tmp_path / "several"  # seed 0 chose source k = 1 of several; seed 1 had one source
    write_run(several, [10, 20, 30], [NAN, 0.9, 0.9], extra={"selected_source": [NAN, 1.0, 1.0]})
    shutil.copy(several / "metrics.csv", root / "target" / "qtl_bayesian" / "m0.6" / "seed_0" / "metrics.csv")
    text = write_report(root).read_text()
    assert "source chosen by compliance (seed_0: 1, seed_1: -)" in text
