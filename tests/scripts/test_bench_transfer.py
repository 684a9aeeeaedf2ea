"""``scripts/bench_transfer.py`` lays its runs out as an experiment directory that ``qtl.report`` reads."""

from __future__ import annotations

import csv
from pathlib import Path

import yaml

from qtl.recorder import METRICS_FILE
from qtl.report import APPROACHES, approach_name, discover
from tests.scripts.load import script

bench_transfer = script("bench_transfer")


def _fake_run(run_dir: Path, returns: list[float]) -> None:
    run_dir.mkdir(parents=True)
    with open(run_dir / METRICS_FILE, "w", newline="") as f:
        writer = csv.DictWriter(f, ["episode", "kind", "return", "success", "compliance"])
        writer.writeheader()
        for episode, value in enumerate(returns):
            writer.writerow({"episode": episode, "kind": "policy" if episode else "random", "return": value,
                             "success": 0, "compliance": "nan"})


def test_every_approach_has_a_preset_and_the_runs_form_an_experiment_directory(tmp_path):
    configs = Path(__file__).resolve().parents[2] / "configs" / "approach"
    assert set(bench_transfer.DEFAULT_APPROACHES) <= set(APPROACHES)  # one approach table: qtl.report's
    assert all((configs / f"{slug}.yaml").is_file() for slug in APPROACHES)
    assert approach_name("qtl_gamma_09").startswith("QTL")  # how the benchmark tells QTL rows from PILCO's
    sources, runs = tmp_path / "sources", tmp_path / "runs"
    for seed in (0, 1):
        _fake_run(sources / f"seed_{seed}", [0.0, 5.0])
        for slug, offset in (("pilco", 0.0), ("qtl_bayesian", 10.0)):
            _fake_run(runs / "target" / slug / "m2.0" / f"seed_{seed}", [offset, offset + seed])
    bench_transfer.link_experiment(runs, sources)
    bench_transfer.link_experiment(runs, sources)  # again: the link stays, the record is rewritten
    assert (runs / "source").resolve() == sources.resolve()
    assert yaml.safe_load((runs / "experiment.yaml").read_text())["name"] == "cartpole transfer benchmark"
    experiment = discover(runs)
    assert experiment.approaches == ["pilco", "qtl_bayesian"]
    assert sorted(experiment.sources) == [0, 1]
    assert experiment.cell("qtl_bayesian", "m2.0").curves[1].returns == [10.0, 11.0]


def test_each_target_mass_keeps_its_own_results():
    assert bench_transfer.result_names(2.0) == ("transfer.json", "bench_transfer")
    assert bench_transfer.result_names(1.5) == ("transfer-m1.5.json", "bench_transfer-m1.5")
    assert bench_transfer.result_names(0.8) == ("transfer-m0.8.json", "bench_transfer-m0.8")
    # A tag (e.g. the particle recipe's runs) keeps its own results beside the moment-matching ones.
    assert bench_transfer.result_names(2.0, "particles") == ("transfer-particles.json", "bench_transfer-particles")
    assert bench_transfer.result_names(1.5, "particles") == ("transfer-m1.5-particles.json",
                                                             "bench_transfer-m1.5-particles")
