"""The report generator on a synthetic experiment directory with hand-computed numbers (Tables 1-6, Figs. 1-3)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from matplotlib.figure import Figure

from qtl.report import autopilot_return, discover, label_order, legend_entries, write_report

REPO = Path(__file__).resolve().parents[1]
NAN = math.nan

# approach -> label -> seed -> (returns, compliance per episode); success is return >= 30.
# Hand-computed numbers (final = mean of the last 3, AUC = trapezoid, TTC = first episode >= 0.95 final):
CARTPOLE = {
    "qtl_bayesian": {
        "m1.5": {
            0: ([20, 30, 40, 40, 40, 40], [NAN, 0.5, 0.5, 0.5, 0.5, 0.6]),  # final 40, AUC 180, TTC 2
            1: ([20, 40, 40, 40, 40, 40], [NAN, 0.7, 0.7, 0.7, 0.7, 0.8]),  # final 40, AUC 190, TTC 1
        },
        "m2.0": {  # no compliance: Table 4 falls back to PILCO's runs
            0: ([10, 20, 20, 20, 20, 20], [NAN] * 6),  # final 20, AUC 95, TTC 1
            1: ([10, 10, 30, 30, 30, 30], [NAN] * 6),  # final 30, AUC 120, TTC 2
        },
    },
    "pilco": {
        "m2.0": {
            0: ([0, 0, 10, 20, 20, 20], [NAN, 0.2, 0.2, 0.2, 0.2, 0.25]),  # final 20, AUC 60, TTC 3
            # 8 episodes, cut to the cell's common 6: final 14, AUC 54, TTC 4 (uncut: final 72);
            # no compliance at episode 5 (0.9 at the cut-off episode 7 must not count).
            1: ([0, 10, 10, 10, 16, 16, 100, 100], [NAN, 0.3, 0.3, 0.3, 0.3, NAN, 0.9, 0.9]),
        },
        "m1.5": {
            0: ([0, 10, 20, 30, 30, 30], [NAN, 0.1, 0.1, 0.1, 0.1, 0.1]),  # final 30, AUC 105, TTC 3
            1: ([0, 36, 20, 36, 36, 36], [NAN, 0.1, 0.1, 0.1, 0.1, 0.1]),  # final 36, AUC 146, TTC 1
        },
    },
}


def write_run(run_dir: Path, returns: list[float], compliance: list[float] | None = None,
              overrides: list[str] | None = None, env: dict | None = None) -> None:
    """A run directory as ``qtl-train`` leaves it: ``metrics.csv``, ``.hydra/overrides.yaml`` (and ``config.yaml``)."""
    compliance = compliance or [NAN] * len(returns)
    (run_dir / ".hydra").mkdir(parents=True)
    rows = ["episode,kind,return,predicted_return,success,compliance"]
    for episode, (ret, comp) in enumerate(zip(returns, compliance, strict=True)):
        kind = "random" if episode == 0 else "policy"
        rows.append(f"{episode},{kind},{ret},nan,{int(ret >= 30)},{'' if math.isnan(comp) else comp}")
    (run_dir / "metrics.csv").write_text("\n".join(rows) + "\n")
    (run_dir / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides or []))
    if env is not None:
        (run_dir / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"seed": 0, "task": {"env": env}}))


def make_experiment(root: Path, runs: dict, sources: int = 2) -> Path:
    for seed in range(sources):
        write_run(root / "source" / f"seed_{seed}", [0.0, 5.0, 9.0, 10.0], overrides=[f"seed={seed}"])
    for approach, by_label in runs.items():
        for label, by_seed in by_label.items():
            for seed, (returns, compliance) in by_seed.items():
                overrides = [f"seed={seed}", f"approach={approach}", f"task.env.pole_mass={label[1:]}"]
                write_run(root / "target" / approach / label / f"seed_{seed}", returns, compliance, overrides)
    return root


@pytest.fixture(scope="module")
def cartpole(tmp_path_factory) -> tuple[Path, str, dict]:
    """The cart-pole experiment's report: (report path, report.md text, tables.json)."""
    root = make_experiment(tmp_path_factory.mktemp("cartpole"), CARTPOLE)
    report = write_report(root)
    return report, report.read_text(), json.loads((report.parent / "tables.json").read_text())


def test_discover_reads_every_cell_cut_to_its_common_episodes(tmp_path):
    experiment = discover(make_experiment(tmp_path, CARTPOLE))
    assert experiment.approaches == ["pilco", "qtl_bayesian"]  # the paper's row order, not the directory's
    assert experiment.labels == ["m1.5", "m2.0"]
    assert sorted(experiment.sources) == [0, 1] and experiment.sources[0].returns == [0.0, 5.0, 9.0, 10.0]
    curves = experiment.curves
    assert curves["pilco"]["m2.0"][1].returns == [0, 10, 10, 10, 16, 16]
    cell = experiment.cell("pilco", "m2.0")
    assert cell is not None and cell.episodes == 6 and cell.truncated and cell.lengths == {0: 6, 1: 8}
    assert not experiment.cell("pilco", "m1.5").truncated
    assert experiment.cell("pilco", "m0.8") is None


def test_labels_sort_numerically_then_by_name():
    labels = ["helicopter", "m10", "m2.0", "p0.5", "m1.5", "m0.8"]
    assert sorted(labels, key=label_order) == ["m0.8", "m1.5", "m2.0", "m10", "p0.5", "helicopter"]


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
    for row in [
        "| Approach | m1.5 | m2.0 | Seeds |",
        "| PILCO (γ = 0) | 33.00 ± 4.24 | 17.00 ± 4.24 | 2 |",  # Table 1
        "| QTL-PILCO Bayesian | 40.00 ± 0.00 | 25.00 ± 7.07 | 2 |",
        "| PILCO (γ = 0) | 125.50 ± 28.99 | 57.00 ± 4.24 | 2 |",  # Table 2
        "| QTL-PILCO Bayesian | 185.00 ± 7.07 | 107.50 ± 17.68 | 2 |",
        "| PILCO (γ = 0) | 2.0 ± 1.4 | 3.5 ± 0.7 | 2 |",  # Table 3
        "| QTL-PILCO Bayesian | 1.5 ± 0.7 | 1.5 ± 0.7 | 2 |",
        "| m1.5 | QTL-PILCO Bayesian | 0.70 ± 0.14 | 2 |",  # Table 4
        "| m2.0 | PILCO (γ = 0) | 0.25 | 1 |",
    ]:
        assert row in text, row
    positions = [text.index(f"**Table {n}.**") for n in (1, 2, 3, 4)]
    assert positions == sorted(positions)
    assert "**Table 5.**" not in text and "**Table 6.**" not in text  # two labels
    assert text.index("| PILCO (γ = 0) | 33.00") < text.index("| QTL-PILCO Bayesian | 40.00")
    # What was found, with the common-prefix rule stated for the one cell it cut.
    assert "seed_0: 6, seed_1: 8" in text and "the common first 6 episodes are used" in text
    assert text.count("the common first") == 1
    # No experiment.yaml: the overrides of one run per cell (and of a source run).
    assert "`qtl-train seed=0 approach=qtl_bayesian task.env.pole_mass=2.0`" in text
    assert "`qtl-train seed=0 approach=pilco task.env.pole_mass=1.5`" in text
    assert "`source/seed_0`: `qtl-train seed=0`" in text
    assert "![learning curves](fig_learning_curves.png)" in text


def test_figures_are_written_as_png_and_pdf(cartpole):
    report, _, _ = cartpole
    png, pdf = report.parent / "fig_learning_curves.png", report.parent / "fig_learning_curves.pdf"
    assert png.stat().st_size > 1000 and png.read_bytes().startswith(b"\x89PNG")
    assert pdf.stat().st_size > 1000 and pdf.read_bytes().startswith(b"%PDF")


def test_a_root_without_target_runs_is_an_error(tmp_path):
    with pytest.raises(ValueError, match=f"{tmp_path}: no target runs"):
        write_report(tmp_path)
    write_run(tmp_path / "source" / "seed_0", [1.0, 2.0])
    (tmp_path / "target" / "pilco" / "m1.5" / "seed_0").mkdir(parents=True)  # started, no metrics yet
    with pytest.raises(ValueError, match="no target runs"):
        write_report(tmp_path)
    assert not (tmp_path / "report").exists()


def test_helicopter_report_has_tables_5_6_and_the_autopilot_line(tmp_path):
    root = tmp_path / "aircraft"
    overrides = ["approach=pilco", "seed=0"]
    env = {"id": "qtl/Helicopter-v0", "mass": 6.0, "horizon": 200}  # as the run's .hydra/config.yaml records it
    write_run(root / "target" / "pilco" / "helicopter" / "seed_0", [0, 50, 100, 130, 130, 130],
              overrides=overrides, env=env)  # final 130, AUC 475, TTC 3
    write_run(root / "target" / "qtl_bayesian" / "helicopter" / "seed_0", [50, 120, 131, 132, 133, 131],
              overrides=overrides)  # final 132, AUC 606.5, TTC 2
    command = "qtl-train -m +experiment=aircraft seed=0,1,2,3,4"
    (root / "experiment.yaml").write_text(yaml.safe_dump({"name": "aircraft", "commands": [command]}))
    report = write_report(root, tmp_path / "out")
    assert report == tmp_path / "out" / "report.md"
    text = report.read_text()
    for row in [
        "| PILCO (γ = 0) | 475.00 | 1 |",  # Table 5
        "| QTL-PILCO Bayesian | 606.50 | 1 |",
        "| PILCO (γ = 0) | 3 (130.00) | 1 |",  # Table 6
        "| QTL-PILCO Bayesian | 2 (132.00) | 1 |",
        "| PILCO (γ = 0) | 130.00 | 1 |",  # Table 1: one seed, just the value
    ]:
        assert row in text, row
    assert "**Table 5.** Area under the learning curve for the helicopter task." in text
    assert "**Table 4.**" not in text  # no run computed compliance
    assert command in text and "QTL-PILCO report: aircraft" in text
    tables = json.loads((tmp_path / "out" / "tables.json").read_text())
    assert sorted(tables["tables"]) == ["1", "2", "3", "5", "6"]
    assert tables["experiment"] == "aircraft"
    # The autopilot flies the runs' helicopter (task.env of the run's .hydra/config.yaml, mass 6.0).
    line = tables["reference"]
    assert line["name"] == "autopilot"
    assert line["return"] == pytest.approx(autopilot_return({"mass": 6.0}))
    assert line["return"] != pytest.approx(autopilot_return())
    assert f"({line['return']:.2f})" in text
    assert (tmp_path / "out" / "fig_learning_curves.png").stat().st_size > 1000
    assert (tmp_path / "out" / "fig_learning_curves.pdf").stat().st_size > 1000


def test_autopilot_return_is_a_finite_positive_total_reward():
    total = autopilot_return()
    assert math.isfinite(total) and 0 < total <= 200  # at most 1 per step over the 200-step horizon
    assert autopilot_return({"id": "qtl/Helicopter-v0"}) == total  # an `id` key (as in task.env) is ignored
    assert autopilot_return(seed=0) == total


def test_cli_prints_the_report_path(tmp_path):
    root = make_experiment(tmp_path / "exp", {"pilco": {"m1.5": CARTPOLE["pilco"]["m1.5"]}}, sources=0)
    done = subprocess.run([sys.executable, str(REPO / "scripts" / "report.py"), str(root), "--out",
                           str(tmp_path / "out")], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(tmp_path / "out" / "report.md")
    assert "| PILCO (γ = 0) | 33.00 ± 4.24 | 2 |" in (tmp_path / "out" / "report.md").read_text()


def test_one_legend_names_the_approaches_of_every_panel():
    # An approach run on the second target only (the 2.0 kg column of seven beside a 1.5 kg column of
    # three) must still be named: the legend on the first panel gathers every panel's entries once.
    first, second = Figure().subplots(1, 2)
    first.plot([0, 1], label="PILCO")
    second.plot([0, 1], label="PILCO")
    second.plot([1, 0], label="Policy transfer")
    handles, labels = legend_entries([first, second])
    assert labels == ["PILCO", "Policy transfer"]
    assert len(handles) == 2
