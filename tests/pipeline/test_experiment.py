"""``qtl-experiment``: a paper experiment as two real Hydra sweeps on the joblib launcher, then its report (tiny)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from qtl.launch import planned_runs
from qtl.pipeline import experiment
from qtl.report import ExperimentRecord, autopilot_return
from qtl.report.progress import sweep_progress
from tests.helpers import BUDGET
from tests.report.fakes import write_run

pytestmark = pytest.mark.e2e  # runs the real CLI in subprocesses: -m 'not e2e' skips it

ROOT = Path(__file__).resolve().parents[2]
COMMAND = [sys.executable, "-m", "qtl.pipeline.experiment"]  # qtl-experiment, as the installed entry point runs it
TINY = ["episodes=1", *BUDGET]


@pytest.fixture(scope="module")
def quick_cartpole(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    root = tmp_path_factory.mktemp("experiment") / "cartpole_quick"
    done = subprocess.run([*COMMAND, "cartpole", "--quick", *TINY, f"sweep.root={root}"], capture_output=True,
                          text=True, timeout=600, cwd=root.parent)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
    return root, done


def test_two_seed_two_episode_sweep_runs_sources_then_targets(quick_cartpole):
    root, done = quick_cartpole
    assert sorted(p.name for p in (root / "source").iterdir() if p.is_dir()) == ["seed_0", "seed_1"]
    targets = sorted(str(p.relative_to(root / "target")) for p in (root / "target").glob("*/*/seed_*"))
    assert targets == [f"{a}/m2.0/seed_{s}" for a in ("pilco", "qtl_bayesian") for s in (0, 1)]
    for run_dir in (root / "target").glob("*/*/seed_*"):
        rows = (run_dir / "metrics.csv").read_text().splitlines()
        assert len(rows) == 1 + 2  # header + 2 episodes
    # QTL runs start from their own seed's source policy; both approaches log compliance against it.
    kinds = {p.parent.parent.name: (p / "metrics.csv").read_text().splitlines()[1].split(",")[1]
             for p in (root / "target").glob("*/*/seed_0")}
    assert kinds == {"pilco": "random", "qtl_bayesian": "source_policy"}
    assert "joblib" in (root / "target" / "multirun.yaml").read_text().lower()
    assert done.stdout.index("[1/2]") < done.stdout.index("[2/2]")


def test_repeated_sweep_continues_instead_of_redoing(quick_cartpole):
    root, _ = quick_cartpole
    before = {p: p.stat().st_mtime_ns for p in root.glob("target/*/*/seed_*/checkpoints/*.pt")}
    again = subprocess.run([sys.executable, "-m", "qtl", "experiment=cartpole_quick", *TINY, f"sweep.root={root}"],
                           capture_output=True, text=True, timeout=600, cwd=root.parent)
    assert again.returncode == 0, again.stderr[-3000:]
    assert {p: p.stat().st_mtime_ns for p in root.glob("target/*/*/seed_*/checkpoints/*.pt")} == before


def test_status_names_every_run_the_real_multirun_made_and_finds_them_finished(quick_cartpole):
    root, _ = quick_cartpole
    made = sorted(p.parent for p in root.glob("*/**/.hydra"))
    planned = planned_runs("cartpole_quick_source", [*TINY, f"sweep.root={root}"]) + planned_runs(
        "cartpole_quick", [*TINY, f"sweep.root={root}"])
    assert sorted(r.run_dir for r in planned) == made
    assert all(p.finished and p.done == 2 for p in sweep_progress(planned))
    status = subprocess.run([*COMMAND, "cartpole", "--quick", "--status", *TINY, f"sweep.root={root}"],
                            capture_output=True, text=True, timeout=300)
    assert status.returncode == 0, status.stderr[-3000:]
    assert "**sources (cartpole_quick_source)**: 2 of 2 runs finished" in status.stdout
    assert "**targets (cartpole_quick)**: 4 of 4 runs finished" in status.stdout


def test_report_of_the_sweep(quick_cartpole):
    root, _ = quick_cartpole
    report = (root / "report" / "report.md").read_text()
    assert "PILCO" in report and "Bayesian" in report and "m2.0" in report
    assert "qtl-train experiment=cartpole_quick_source" in report
    assert json.loads((root / "report" / "tables.json").read_text())
    assert (root / "report" / "fig_learning_curves.png").stat().st_size > 0


def test_the_aircraft_driver_records_the_autopilot_line_before_the_report(tmp_path, monkeypatch):
    # The two sweeps are stood in for: stage 2 leaves helicopter runs as the aircraft_quick preset would.
    root = tmp_path / "aircraft_quick"
    helicopter = {"id": "qtl/Helicopter-v0"}  # task.horizon: the quick preset's 6 s episodes (60 steps)
    stages = []

    def sweep(command: list[str], check: bool) -> None:
        stages.append(command[3])
        if command[3] == "experiment=aircraft_quick":
            for approach in ("pilco", "qtl_bayesian"):
                write_run(root / "target" / approach / "helicopter" / "seed_0", [0.0, 20.0, 30.0],
                          overrides=[f"approach={approach}", "seed=0"], env=helicopter, horizon=60)

    monkeypatch.setattr(experiment.subprocess, "run", sweep)
    monkeypatch.chdir(tmp_path)  # run from above the sweep: experiment.yaml names it relative, not as this machine's
    experiment.main(["aircraft", "--quick", f"sweep.root={root}"])
    assert stages == ["experiment=aircraft_quick_source", "experiment=aircraft_quick"]
    record = ExperimentRecord.read(root)
    assert record.name == "aircraft" and len(record.commands) == 2
    assert record.commands[1] == "qtl-train experiment=aircraft_quick sweep.root=aircraft_quick"
    assert record.reference is not None and record.reference.name == "autopilot"
    assert record.reference.total == pytest.approx(autopilot_return({"horizon": 60}))
    assert record.reference.total != pytest.approx(autopilot_return())  # the runs' 60-step episodes, not 200
    tables = json.loads((root / "report" / "tables.json").read_text())
    assert tables["reference"] == {"name": "autopilot", "return": record.reference.total}
    assert "reference" in yaml.safe_load((root / "experiment.yaml").read_text())


def test_a_sweep_kept_without_its_checkpoints_is_refused_before_anything_runs(tmp_path, monkeypatch, capsys):
    # A finished sweep in git keeps its CSVs, not its checkpoints (docs/experiments/README.md): resume=auto would
    # start its runs afresh over the kept files.
    root = tmp_path / "cartpole_quick"
    write_run(root / "source" / "seed_0", [0.0, 5.0])

    def sweep(command: list[str], check: bool) -> None:
        raise AssertionError(f"ran {command}")

    monkeypatch.setattr(experiment.subprocess, "run", sweep)
    with pytest.raises(SystemExit) as stop:
        experiment.main(["cartpole", "--quick", f"sweep.root={root}"])
    err = capsys.readouterr().err
    assert stop.value.code == 1 and err.count("\n") == 1 and err.startswith("qtl-experiment: 1 run(s) under")
    assert "(e.g. source/seed_0)" in err and "another sweep.root" in err
    assert not (root / "experiment.yaml").exists()


@pytest.mark.parametrize(("argv", "says"), [
    (["nope=1"], "Could not override 'nope'"),  # a key the config lacks
    (["approach=nope"], "Could not find 'approach/nope'"),  # an option the group lacks
    (["--sweep-root=x"], "unrecognised option(s) --sweep-root=x"),  # a mistyped option, not an override
])
def test_bad_input_is_refused_in_one_line_before_anything_runs(tmp_path, monkeypatch, capsys, argv, says):
    def sweep(command: list[str], check: bool) -> None:
        raise AssertionError(f"ran {command}")

    monkeypatch.setattr(experiment.subprocess, "run", sweep)
    with pytest.raises(SystemExit) as stop:
        experiment.main(["cartpole", "--quick", f"sweep.root={tmp_path / 'x'}", *argv])
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert stop.value.code == 2 and last.startswith("qtl-experiment: error:") and says in last
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("preset", sorted(p.stem for p in (ROOT / "configs" / "experiment").glob("*.yaml")
                                          if not p.stem.endswith("_source")))
def test_sweeps_launch_every_approach_of_a_target_and_seed_together(preset):
    # Hydra launches the product of the sweeper's params with the last key innermost: with the approaches last, a
    # sweep stopped part-way (sweeps span sessions) leaves whole comparisons, not one approach's runs only.
    params = yaml.safe_load((ROOT / "configs" / "experiment" / f"{preset}.yaml").read_text())["hydra"]["sweeper"]
    assert list(params["params"])[-1] == "approach"


@pytest.mark.parametrize("preset", sorted(p.stem for p in (ROOT / "configs" / "experiment").glob("*.yaml")
                                          if "_quick" not in p.stem))
def test_full_scale_presets_go_sparse_above_300_tuples_as_pilco_does(preset):
    # PILCO's train.m trains FITC with its 300 pseudo-inputs as soon as the data exceed them; the paper ran PILCO.
    # Source and target presets must agree, or a target's GP would differ from its source's in kind.
    from hydra import compose, initialize_config_module

    from qtl.config import register_configs

    register_configs()
    with initialize_config_module(config_module="qtl.configs", version_base="1.3"):
        model = compose(config_name="train", overrides=[f"experiment={preset}"]).model
    assert (model.sparse_above, model.inducing) == (300, 300)
