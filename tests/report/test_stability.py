"""Tables S4-S5 (hyper-parameter change per model update) on synthetic runs with hand-computed θ paths."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from qtl.report import write_report
from qtl.report.discover import discover
from qtl.report.stability import stability_markdown, stability_values, theta_changes, theta_path
from tests.report.fakes import NAN, table_rows, write_run

A = "theta/out0/lengthscale/in0"
B = "theta/out0/noise_variance"
P = "theta_p/out0/noise_variance"  # evidence maximisation's θ_p: not what the model used, so never read


def _exp(logs: list[float]) -> list[float]:
    return [math.exp(v) if not math.isnan(v) else NAN for v in logs]


# approach -> seed -> (returns, {column: log θ per episode}); episode 0 has no model.
RUNS = {
    "pilco": {
        # updates (mean |Δ log θ| over A and B): 0.5, 1, 1, 0, 0, 0.5
        0: ([0, 10, 20, 30, 30, 30, 30, 30], {A: [NAN, 0, 1, 3, 3, 3, 3, 4], B: [NAN, 0, 0, 0, 2, 2, 2, 2],
                                               P: [NAN, 9, -9, 9, -9, 9, -9, 9]}),
        1: ([0, 10, 20, 30, 30, 30, 30, 30], {A: [NAN, 1] + [1] * 6, B: [NAN, 2] + [2] * 6}),  # never moves
    },
    "qtl_bayesian": {
        # seed 1 has 6 episodes, so seed 0 is cut to its first 6 and its jump at episode 6 is not counted
        0: ([0, 10, 20, 30, 30, 30, 30, 30], {A: [NAN, 0, 0.5, 1, 1.5, 2, 100, 100]}),  # 0.5 per update
        1: ([0, 10, 20, 30, 30, 30], {A: [NAN, 0, 0, 0, 0, 0]}),
    },
}


def _make(root: Path, runs: dict = RUNS, no_theta: bool = False) -> Path:
    """Sources and the target runs of ``runs`` on one label (``m2.0``); ``no_theta`` adds a PILCO seed without θ."""
    for seed in range(2):
        write_run(root / "source" / f"seed_{seed}", [0.0, 5.0, 9.0, 10.0], overrides=[f"seed={seed}"])
    for approach, by_seed in runs.items():
        for seed, (returns, logs) in by_seed.items():
            write_run(root / "target" / approach / "m2.0" / f"seed_{seed}", returns,
                      overrides=[f"seed={seed}", f"approach={approach}"],
                      extra={column: _exp(values) for column, values in logs.items()})
    if no_theta:
        write_run(root / "target" / "pilco" / "m2.0" / "seed_2", [0, 10, 20, 30, 30, 30, 30, 30])
    return root


@pytest.fixture(scope="module")
def experiment(tmp_path_factory: pytest.TempPathFactory):
    """The runs of :data:`RUNS` (and a PILCO run that logged no θ), discovered."""
    return discover(_make(tmp_path_factory.mktemp("stability"), no_theta=True))


def test_theta_path_reads_the_models_theta_only(experiment):
    cell = experiment.cell("pilco", "m2.0")
    thetas = theta_path(cell.run_dirs[0], cell.episodes)
    assert thetas.shape == (7, 2)  # episodes 1-7 (episode 0 had no model); A and B, not θ_p
    np.testing.assert_allclose(np.log(thetas[:, 0]), [0, 1, 3, 3, 3, 3, 4], atol=1e-12)
    assert theta_path(cell.run_dirs[2], cell.episodes).shape[1] == 0


def test_changes_are_mean_absolute_log_steps():
    thetas = np.exp(np.array([[0.0, 0.0], [1.0, 0.0], [3.0, 2.0], [3.0, 2.0]]))
    np.testing.assert_allclose(theta_changes(thetas), [0.5, 2.0, 0.0], atol=1e-12)
    with pytest.raises(ValueError, match="non-positive"):
        theta_changes(np.array([[1.0], [0.0]]))


def test_per_seed_values_are_hand_computed(experiment):
    values = stability_values(experiment).set_index(["metric", "approach", "label", "seed"])["value"]
    assert values[("early", "pilco", "m2.0", 0)] == pytest.approx(0.5)  # mean of 0.5, 1, 1, 0, 0
    assert values[("late", "pilco", "m2.0", 0)] == pytest.approx(0.5)  # the sixth update
    assert values[("early", "pilco", "m2.0", 1)] == pytest.approx(0.0)
    assert values[("early", "qtl_bayesian", "m2.0", 0)] == pytest.approx(0.5)  # cut: the jump to 100 is not seen
    assert ("late", "qtl_bayesian", "m2.0", 0) not in values.index  # 4 updates only: no later part
    assert ("early", "pilco", "m2.0", 2) not in values.index  # no θ logged: left out, not counted as 0
    split = stability_values(experiment, early=2).set_index(["metric", "approach", "label", "seed"])["value"]
    assert split[("early", "pilco", "m2.0", 0)] == pytest.approx(0.75)
    assert split[("late", "pilco", "m2.0", 0)] == pytest.approx(0.375)


def test_markdown_cells(experiment):
    rows = table_rows("\n\n".join(stability_markdown(experiment)))
    spread = math.sqrt(2 * 0.25**2)  # ddof = 1 over the seeds' 0.5 and 0.0
    assert ("PILCO (γ = 0)", f"0.250 ± {spread:.3f}", "2") in rows  # S4
    assert ("QTL-PILCO Bayesian", f"0.250 ± {spread:.3f}", "2") in rows
    assert ("PILCO (γ = 0)", f"0.250 ± {spread:.3f}", "2") in rows  # S5: seeds 0.5 and 0.0 again
    assert ("QTL-PILCO Bayesian", "—", "—") in rows  # no run long enough for a later update


def test_report_holds_the_tables_and_their_numbers(tmp_path):
    report = write_report(_make(tmp_path))
    text = report.read_text()
    assert "## Hyper-parameter stability (not in the paper)" in text
    assert text.index("**Table S4.**") < text.index("**Table S5.**")
    stability = json.loads((report.parent / "tables.json").read_text())["stability"]
    assert stability["early_updates"] == 5
    assert stability["early"]["pilco"]["m2.0"]["per_seed"] == {"0": pytest.approx(0.5), "1": pytest.approx(0.0)}
    assert stability["late"]["pilco"]["m2.0"]["mean"] == pytest.approx(0.25)
    assert "qtl_bayesian" not in stability["late"]


def test_runs_without_theta_leave_the_tables_out(cartpole):
    _, text, tables = cartpole
    assert "Table S4" not in text and tables["stability"] is None
