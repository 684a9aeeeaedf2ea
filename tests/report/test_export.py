"""``qtl-report ROOT --export DIR``: a finished experiment's small files, from which the same report is rebuilt."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from omegaconf import OmegaConf

from qtl.loop import run
from qtl.report import ExperimentRecord, write_report
from qtl.report.cli import main
from qtl.report.export import EXPERIMENT_FILES, REPORT_FILES, RUN_FILES
from qtl.report.final_policies import FINAL_POLICIES_FILE
from qtl.report.paths import recorded_path
from qtl.report.progress import PlannedRun, sweep_progress
from tests.helpers import tiny_config
from tests.report.fakes import CARTPOLE, make_experiment

REPO = Path(__file__).resolve().parents[2]
RUNS = ("source/seed_0", "target/pilco/m0.5/seed_0", "target/pilco/m0.5/seed_1")
HEAVY = ("*.pt", "events.out.tfevents.*", "*.log", "hydra.yaml", "multirun.yaml")  # what a run leaves, too big


def _real_run(root: Path, name: str) -> None:
    """A tiny real run (1 random + 1 learned episode: metrics, timings, health, checkpoints, events), with the
    ``.hydra/`` record, ``train.log`` and the sweep's ``multirun.yaml`` that ``qtl-train`` leaves beside it."""
    run_dir = root / name
    seed = int(name.rsplit("_", 1)[1])
    cfg = tiny_config("episodes=1", f"seed={seed}")
    run(cfg, run_dir)
    overrides = [f"seed={seed}"] if name.startswith("source") else [f"seed={seed}", "approach=pilco",
                                                                     "task.env.pole_mass=0.5"]
    (run_dir / ".hydra").mkdir()
    (run_dir / ".hydra" / "config.yaml").write_text(OmegaConf.to_yaml(cfg))
    (run_dir / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    (run_dir / ".hydra" / "hydra.yaml").write_text(yaml.safe_dump({"hydra": {"runtime": {"cwd": str(root)}}}))
    (run_dir / "train.log").write_text("[qtl.train][INFO] - 2 episodes\n")
    (root / name.split("/")[0] / "multirun.yaml").write_text(yaml.safe_dump({"hydra": {"mode": "MULTIRUN"}}))


@pytest.fixture(scope="module")
def experiment(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finished experiment of real runs, with its experiment.yaml, final_policies.json and report."""
    root = tmp_path_factory.mktemp("original") / "cartpole"
    for name in RUNS:
        _real_run(root, name)
    ExperimentRecord(name="cartpole", commands=["qtl-train experiment=cartpole sweep.root=x"]).write(root)
    runs = [{"approach": "source" if name.startswith("source") else "pilco",
             "label": "source" if name.startswith("source") else "m0.5", "seed": int(name[-1]), "episode": 1,
             "success_rate": 0.5, "mean_return": 1.0 + k, "returns": [0.5 + k, 1.5 + k]} for k, name in enumerate(RUNS)]
    (root / FINAL_POLICIES_FILE).write_text(json.dumps({"starts": 2, "eval_seed": 7, "runs": runs}))
    write_report(root)
    return root


def _files(folder: Path) -> set[str]:
    return {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()}


def _heavy(folder: Path) -> set[str]:
    return {p.relative_to(folder).as_posix() for pattern in HEAVY for p in folder.rglob(pattern)}


def _without_root(tables: Path) -> dict:
    """tables.json but for ``root``, where the experiment lies (the export elsewhere)."""
    found = json.loads(tables.read_text())
    del found["root"]
    return found


def test_the_export_holds_the_small_files_only_and_rebuilds_the_same_report(experiment, tmp_path, capsys):
    assert {"source/seed_0/checkpoints/episode_0001.pt", "target/multirun.yaml",
            "target/pilco/m0.5/seed_1/train.log"} <= _heavy(experiment)  # the source has them ...
    assert any("events.out.tfevents" in name for name in _heavy(experiment))
    dest = tmp_path / "export"
    main([str(experiment), "--export", str(dest)])
    expected = ({p.as_posix() for p in (*EXPERIMENT_FILES, *REPORT_FILES)}
                | {f"{run}/{p.as_posix()}" for run in RUNS for p in RUN_FILES})
    assert _files(dest) == expected
    assert capsys.readouterr().out.strip() == f"{dest} ({len(expected)} files)"
    assert not _heavy(dest)  # ... the export none
    for name in expected:
        assert (dest / name).read_bytes() == (experiment / name).read_bytes(), name
    # The report rebuilt from the export is the original's: the same numbers, the same text (but for where it lies).
    again, first = write_report(dest, tmp_path / "from_export"), write_report(experiment, tmp_path / "from_original")
    assert _without_root(again.parent / "tables.json") == _without_root(first.parent / "tables.json")
    assert _without_root(again.parent / "tables.json") == _without_root(experiment / "report" / "tables.json")

    def text(report: Path, root: Path) -> str:  # where the experiment lies, as the report names it, left out
        return report.read_text().replace(recorded_path(root), "<root>")

    assert text(again, dest) == text(first, experiment)
    assert "**Table F1.**" in again.read_text()  # final_policies.json came along
    # Where the sweep stands reads the export's runs as finished, though they hold no checkpoint.
    plan = [PlannedRun(dest / name, (), episodes=2) for name in RUNS]
    assert all(p.finished and p.done == 2 for p in sweep_progress(plan))


def test_an_existing_folder_that_is_not_empty_is_refused_in_one_line_writing_nothing(experiment, tmp_path, capsys):
    dest = tmp_path / "export"
    dest.mkdir()
    (dest / "notes.txt").write_text("mine\n")
    with pytest.raises(SystemExit) as stop:
        main([str(experiment), "--export", str(dest)])
    err = capsys.readouterr().err
    assert stop.value.code == 1 and err.count("\n") == 1 and "exists and is not an empty folder" in err
    assert _files(dest) == {"notes.txt"}
    main([str(experiment), "--export", str(tmp_path / "empty")])  # an empty folder is fine (nothing to overwrite)
    (tmp_path / "empty2").mkdir()
    main([str(experiment), "--export", str(tmp_path / "empty2")])
    assert _files(tmp_path / "empty2") == _files(tmp_path / "empty")


def test_an_unfinished_run_is_refused_unless_finished_only(tmp_path, capsys):
    root = make_experiment(tmp_path / "sweep", CARTPOLE)  # pilco/m2.0/seed_1 has 8 episodes, the others 6 (4 sources)
    for config in ("target/*/*/seed_*", "source/seed_*"):
        for run_dir in root.glob(config):
            wanted = 6 if run_dir.parent.name != "source" else 4  # random + learned episodes
            (run_dir / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"random_episodes": 1,
                                                                            "episodes": wanted - 1}))
    unfinished = root / "target" / "qtl_bayesian" / "m1.5" / "seed_1"
    (unfinished / ".hydra" / "config.yaml").write_text(yaml.safe_dump({"random_episodes": 1, "episodes": 9}))
    with pytest.raises(SystemExit) as stop:
        main([str(root), "--export", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert stop.value.code == 1 and err.count("\n") == 1
    assert "1 unfinished run(s), target/qtl_bayesian/m1.5/seed_1 (6 of 10 episodes)" in err and "--finished-only" in err
    assert not (tmp_path / "out").exists()
    main([str(root), "--export", str(tmp_path / "out"), "--finished-only"])
    exported = _files(tmp_path / "out")
    assert "target/qtl_bayesian/m1.5/seed_0/metrics.csv" in exported
    assert not any(name.startswith("target/qtl_bayesian/m1.5/seed_1/") for name in exported)
    assert "source/seed_1/.hydra/config.yaml" in exported and "report/report.md" not in exported  # none written


def test_export_takes_neither_out_nor_record_reference(tmp_path, capsys):
    for extra in (["--out", str(tmp_path / "r")], ["--record-reference"]):
        with pytest.raises(SystemExit) as stop:
            main([str(tmp_path), "--export", str(tmp_path / "out"), *extra])
        assert stop.value.code == 2 and "--export copies the experiment as it is" in capsys.readouterr().err


def test_qtl_report_is_the_package_cli_and_no_script_wraps_it():
    scripts = (REPO / "pyproject.toml").read_text().split("[project.scripts]")[1].split("\n[")[0]
    assert 'qtl-report = "qtl.report.cli:main"' in scripts.splitlines()
    assert not (REPO / "scripts" / "report.py").exists()
